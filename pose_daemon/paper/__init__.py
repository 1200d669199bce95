"""The paper's results reproduced (Kothari et al., ICC 2017): Tables I-II, the orientation
sweep of Fig. 4 and the unicycle robot of Figs. 7-9, on the project's estimator."""
