"""Pure numpy/scipy estimation math: linear algebra, Kalman/EKF, information and log-det gains."""
