"""Shared fixtures."""

from __future__ import annotations

import numpy as np
import pytest

from pose_daemon import Camera, Marker


@pytest.fixture
def camera() -> Camera:
    return Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)


@pytest.fixture
def marker() -> Marker:
    return Marker(width=0.20, height=0.20)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
