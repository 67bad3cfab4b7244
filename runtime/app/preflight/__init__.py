"""`dct preflight`: is this computer ready to drive this robot? Checked before driving.

Each check gives one line, PASS / WARN / FAIL, what was seen and, when not PASS, how to fix it.
A FAIL is something the robot cannot drive without (a file that does not load, a distance net
for another footprint, a CAN bus that is down, a base that does not answer, a silent sensor,
too little disk for the logs); a WARN is something that makes the drive worse but not unsafe
(no clock sync, a power-saving CPU governor, no SCHED_FIFO: the loop then runs SCHED_OTHER and
counts its lateness as always). The exit code is 0 only when no check FAILs.

Checks, in order (names as in the JSON):
- files: `robot`, `config`, `calibration` (for this robot's camera: robot name, image size,
  lidar->camera extrinsic close to the robot description's mounts), `calibration:mounts` (the
  calibrated sensors lie on the robot's body), `distance_net` (loads and its footprint is the
  robot's, models.distance_net.DistanceNet.load);
- CAN: `can_link` (SocketCAN: /sys/class/net/<if>/operstate up and the bit rate from
  `ip -details -json link show` equal to the robot description's; udp_multicast / virtual /
  limo_serial: the bus opens), `base` (0x221 within 100 ms of the enable frame 0x421 that the
  controller sends at start, then 0x211: not in E-stop, no error that stops the controller);
- ROS 2 set-up: `ros:install` (with a bundle's MANIFEST.json: its ROS 2 wheels import from the
  venv, or the robot's ROS 2 imports after sourcing its setup script, or cyclonedds alone),
  `ros:middleware` (what `dct run` will use; rclpy's version or why it does not import),
  `ros:discovery` (open to the network: any host there can publish a goal), `ros:security`
  (SROS2's keystore and enclave files, or goals are unauthenticated);
- sensors: `topic:<stream>` for the lidar, IMU and camera topics of the config's `ros:` section
  (runtime.io.ros RosInputConfig; without one, `topics.default_topics`), heard for `listen_s`
  through the configured middleware and judged against their nominal rates; the last sample of
  each must decode; `match:<stream>` for every input topic (the goal's too): the graph's
  publishers have the configured type and QoS DDS will match; `ros:clock`: the sensors' stamps
  are within 50 ms of this computer's clock; `calibration:intrinsics` and `calibration:floor`:
  the calibration `dct run` would use against the last CameraInfo and lidar frame heard, as the
  controller checks it while driving (`calibration_live`);
- host: `clock_sync`, `cpus`, `cpu_governor`, `sched_fifo`, `cpu_affinity`, `disk`.

Modules: `check` (the result of one check), `files`, `can_bus` (link and base), `ros_setup` (the
ROS 2 set-up), `topics` (sensor topics), `ros_graph` (publishers' types and QoS, the stamps),
`calibration_live` (the calibration against live data), `computer` (clock, CPUs, real-time
scheduling, disk), `run` (every check in order, the summary),
`cli` (the `dct preflight` command).

Everything that touches the machine takes its source as an argument (the /sys root, the `ip`
and clock commands, the bus), so that tests can fake a robot computer.
"""
