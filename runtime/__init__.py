"""The controller: fixed-rate loop, stages (odometry, VPP, planner, MPC), safety, telemetry, `dct`."""
