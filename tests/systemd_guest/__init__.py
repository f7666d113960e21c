"""The systemd units under a real systemd (PID 1) in a User-Mode Linux guest."""
