"""The TurtleBot 3 OpenCR firmware's control table and figures, shared by the client and the simulator.

One place for every address and unit, each checked against the public
sources (kept here so a firmware update is a one-file review):

* Firmware ("turtlebot3_ros2" Arduino library of the OpenCR board), file
  ``ROBOTIS-GIT/OpenCR: arduino/opencr_arduino/opencr/libraries/turtlebot3_ros2/src/turtlebot3/turtlebot3.cpp``:
  ``ID_DXL_SLAVE = 200``, ``MODEL_NUM_DXL_SLAVE = 0x5000``, protocol 2.0,
  ``HEARTBEAT_TIMEOUT_MS = 500`` (a heartbeat byte that stops changing for
  500 ms zeroes the commanded velocity), ``enum ControlTableItemAddr``
  (the addresses below), the write callback (cmd velocity int32 x 0.01 ->
  m/s and rad/s, clamped to the model's limits; torque byte -> motors), the
  write-protection ranges, model info (Burger 1, wheel radius 0.033 m,
  separation 0.160 m, turning radius 0.080 m, 61 rpm; Waffle 2, 0.033 m,
  0.287 m, 0.1435 m, 77 rpm).
* Wheel motors, same library, ``turtlebot3_motor_driver.cpp``: wheel
  velocity -> XL/XM430 goal velocity units ``v * 1263.632956882`` (0.229 rpm
  per unit, r = 0.033 m), truncated to int32 and clamped to +-337; left
  motor id 1, right id 2, both forward-positive in the table.
* ROS 2 node, ``ROBOTIS-GIT/turtlebot3: turtlebot3_node/include/turtlebot3_node/control_table.hpp``
  (same addresses and lengths), ``turtlebot3_node/src/turtlebot3.cpp``
  (device id 200 at 1 000 000 baud, heartbeat written every 100 ms with an
  incrementing count, cmd_vel written as one block 150..173 with
  ``int32(linear.x * 100)`` / ``int32(angular.z * 100)``), and
  ``.../sensors/joint_state.hpp`` (``TICK_TO_RAD = 0.001533981`` =
  2 pi / 4096, present velocity unit 0.229 rpm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

DEVICE_ID = 200
MODEL_NUMBER = 0x5000
BAUDRATE = 1_000_000
HEARTBEAT_TIMEOUT_S = 0.5

# Control table addresses (firmware enum ControlTableItemAddr == node control_table.hpp).
ADDR_MODEL_NUMBER = 0          # uint16
ADDR_MODEL_INFORMATION = 2     # uint32: 1 Burger, 2 Waffle
ADDR_FIRMWARE_VERSION = 6      # uint8
ADDR_ID = 7                    # uint8
ADDR_BAUDRATE = 8              # uint8 (3 = 1 Mbaud)
ADDR_MILLIS = 10               # uint32
ADDR_DEVICE_STATUS = 18        # int8: -1 = wheel motors not connected
ADDR_HEARTBEAT = 19            # uint8, must change at least every 500 ms
ADDR_BUMPER_1 = 28             # uint8 (optional touch sensor)
ADDR_BUMPER_2 = 29             # uint8
ADDR_BATTERY_VOLTAGE = 42      # uint32, V x 100
ADDR_PRESENT_CURRENT_L = 120   # int32
ADDR_PRESENT_CURRENT_R = 124   # int32
ADDR_PRESENT_VELOCITY_L = 128  # int32, 0.229 rpm
ADDR_PRESENT_VELOCITY_R = 132  # int32, 0.229 rpm
ADDR_PRESENT_POSITION_L = 136  # int32 ticks, 4096 per wheel revolution
ADDR_PRESENT_POSITION_R = 140  # int32 ticks
ADDR_MOTOR_TORQUE_ENABLE = 149  # uint8
ADDR_CMD_VELOCITY_LINEAR_X = 150   # int32, 0.01 m/s
ADDR_CMD_VELOCITY_ANGULAR_Z = 170  # int32, 0.01 rad/s
ADDR_PROFILE_ACCELERATION_R = 178  # uint32 (last writable item: 149..181)

TABLE_SIZE = 362               # analog_a5 (360, 2 bytes) is the node's last item

#: Writable ranges (address, length): the firmware write-protects 0..255 and opens these.
WRITABLE = ((ADDR_HEARTBEAT, 1), (20, 4), (50, 1), (59, 1),
            (ADDR_MOTOR_TORQUE_ENABLE, ADDR_PROFILE_ACCELERATION_R + 4 - ADDR_MOTOR_TORQUE_ENABLE))

CMD_VELOCITY_SCALE = 0.01          # one unit of cmd_velocity_* (m/s or rad/s)
TICKS_PER_REV = 4096
TICK_TO_RAD = 2.0 * math.pi / TICKS_PER_REV   # 0.001533981 in the node and firmware
VELOCITY_UNIT_RPM = 0.229
VELOCITY_UNIT_RAD_S = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0
GOAL_VELOCITY_PER_M_S = 1263.632956882   # firmware VELOCITY_CONSTANT_VALUE (r = 0.033 m)
GOAL_VELOCITY_LIMIT = 337                # firmware LIMIT_X_MAX_VELOCITY

#: The block the client reads per feedback: device_status (18) .. present_position_right end (144).
FEEDBACK_ADDR = ADDR_DEVICE_STATUS
FEEDBACK_LEN = ADDR_PRESENT_POSITION_R + 4 - ADDR_DEVICE_STATUS


@dataclass(frozen=True)
class TB3Model:
    """One TurtleBot 3 model as the firmware knows it."""

    name: str
    model_information: int
    wheel_radius_m: float
    track_m: float              # the firmware's wheel_separation
    turning_radius_m: float
    motor_rpm: float

    @property
    def max_linear_m_s(self) -> float:
        """The firmware clamps cmd linear x to this (wheel_radius * 2 pi * rpm / 60)."""
        return self.wheel_radius_m * 2.0 * math.pi * self.motor_rpm / 60.0

    @property
    def max_angular_rad_s(self) -> float:
        """The firmware clamps cmd angular z to max_linear / turning_radius."""
        return self.max_linear_m_s / self.turning_radius_m


MODELS: dict[str, TB3Model] = {
    "burger": TB3Model("burger", 1, 0.033, 0.160, 0.080, 61.0),
    "waffle": TB3Model("waffle", 2, 0.033, 0.287, 0.1435, 77.0),
}
MODEL_BY_INFORMATION = {m.model_information: m for m in MODELS.values()}
