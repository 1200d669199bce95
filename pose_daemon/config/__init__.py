"""TOML configuration -> one typed, validated ``Config``; every mistake is one line naming file and key.

sections.py holds the tables and their keys, each key's rule made by rules.py; load.py reads
and validates the whole (mapsection.py the [map] table); reference.py lists every key for
docs/config.md; forms.py owns the strings a config names things with (sources, links), below
both config and the modules that open what they name.
"""

from .load import (
    DEFAULT_CONFIG_FILE,
    Config,
    ConfigError,
    check_whole,
    config_from_dict,
    default_config_text,
    load_config,
    load_config_or_default,
    parse_config,
    tomllib,
)
from .reference import reference
from .sections import (
    AttitudeConfig,
    CameraConfig,
    DetectorConfig,
    EstimatorConfig,
    GateConfig,
    JsonlOutputConfig,
    LoggingConfig,
    MapConfig,
    MarkerConfig,
    MavlinkOutputConfig,
    MountConfig,
    OutputConfig,
    PipelineConfig,
    PreviewConfig,
    SerialOutputConfig,
    SitlConfig,
    SyntheticConfig,
)

__all__ = [
    "Config",
    "CameraConfig",
    "MarkerConfig",
    "EstimatorConfig",
    "DetectorConfig",
    "SyntheticConfig",
    "PipelineConfig",
    "MountConfig",
    "AttitudeConfig",
    "GateConfig",
    "MavlinkOutputConfig",
    "SerialOutputConfig",
    "JsonlOutputConfig",
    "OutputConfig",
    "LoggingConfig",
    "MapConfig",
    "PreviewConfig",
    "SitlConfig",
    "ConfigError",
    "DEFAULT_CONFIG_FILE",
    "check_whole",
    "config_from_dict",
    "default_config_text",
    "load_config",
    "load_config_or_default",
    "parse_config",
    "reference",
    "tomllib",
]
