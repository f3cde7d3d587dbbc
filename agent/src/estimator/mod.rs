//! Home of the single-robot sliding-window estimator (MSCKF + SLAM features, FEJ,
//! online calibration). It takes no I/O: see the estimator issue for its contents.
