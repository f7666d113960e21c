"""Experiments around the monitor, apart from the daemon: the paper's DC-motor
reproduction (`reproduce`), the demo of a virtual ECU and the monitor on one in-process bus
(`demo`), the scoring of a diagnosis against ground truth (`scoring`) and the baseline
estimator (`akf`, the augmented-state Kalman filter). Figures need the `experiments` extra
(matplotlib); the `demo` and `reproduce` commands reach `motor-monitor` through the
`motor_monitor.commands` entry-point group."""
