"""Commands: priority mux, kinematics and odometry, steering (pure logic, no I/O)."""
