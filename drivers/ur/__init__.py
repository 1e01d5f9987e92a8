"""Universal Robots controllers: RTDE (Real-Time Data Exchange, TCP 30004) for the robot's state
and URScript on the script port (30002) for moves; set-points streamed through RTDE input registers
to a servoj program (`urscript.servo_program`). `protocol` is the RTDE codec, `urscript` the
few commands sent, `driver` the RobotController. The controller serving both ports on loopback over the simulated
plant is `emulators.ur`, so the same driver and tests run against it and a real UR.
"""
