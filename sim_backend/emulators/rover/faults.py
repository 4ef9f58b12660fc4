"""Fault switches of the loopback ArduPilot-Rover emulator, each what ArduPilot / MAVLink users reported."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RoverFaults:
    """Fault switches a test may flip at any time, each what ArduPilot / MAVLink users reported.

    - ``no_heartbeat``: the autopilot's HEARTBEATs stop (everything else keeps working).
    - ``reject_arm`` / ``reject_disarm``: the arm / disarm is refused with ``MAV_RESULT_FAILED``, as
      ArduPilot answers an arm or disarm that fails (pre-arm checks failing, a disarm refused):
      ``GCS_MAVLINK::handle_command_component_arm_disarm``, libraries/GCS_MAVLink/GCS_Common.cpp (before
      it moved there: ``GCS_MAVLINK_Rover::handle_command_long_packet``, APMrover2/GCS_Mavlink.cpp).
    - ``lost_acks`` (command ids): the command takes effect, its ACK is never sent
      (github.com/PX4/PX4-Autopilot/issues/8924, github.com/mavlink/mavros/issues/1590).
    - ``duplicate_acks``: every ACK twice (github.com/mavlink/qgroundcontrol/issues/2975,
      github.com/mavlink/mavlink/pull/768, github.com/PX4/PX4-Autopilot/pull/27343).
    - ``ack_delay_s``: every ACK this late, the command applied at once; a late ACK is read as the answer
      to a later command with the same id (github.com/PX4/PX4-Autopilot/issues/12685).
    - ``ack_accepted_but_ignored`` (command ids): ACCEPTED but not applied
      (github.com/ArduPilot/ardupilot/issues/1385; github.com/PX4/PX4-Autopilot/issues/26034).
    - ``drop_commands``: the next N COMMAND_LONG / SET_MODE are lost on the way in (counted in
      ``dropped_commands``), so the sender must re-send (github.com/mavlink/mavlink/issues/2198);
      ``drop_command_ids``, when not empty, limits that loss to those command ids (a SET_MODE message
      counts as ``MAVLINK_MSG_ID_SET_MODE``) so that a test picks which command is lost.
    - ``companion_heartbeat``: a companion computer (component 191, ``MAV_TYPE_ONBOARD_CONTROLLER``,
      ``MAV_AUTOPILOT_INVALID``, mode 0, disarmed) also beats, just before the autopilot, even with
      ``no_heartbeat`` (github.com/mavlink/MAVSDK/pull/516, github.com/ArduPilot/pymavlink/pull/87).
    - ``drop_param_replies`` / ``duplicate_param_replies``: PARAM_VALUE lost / sent twice.
    """

    no_heartbeat: bool = False
    reject_arm: bool = False
    reject_disarm: bool = False
    lost_acks: set[int] = field(default_factory=set)  # COMMAND_ACK.command ids never answered
    duplicate_acks: bool = False
    ack_delay_s: float = 0.0
    ack_accepted_but_ignored: set[int] = field(default_factory=set)  # ACCEPTED, but nothing happens
    drop_commands: int = 0  # the next N COMMAND_LONG / SET_MODE never arrive
    drop_command_ids: set[int] = field(default_factory=set)  # empty: any command counts for drop_commands
    companion_heartbeat: bool = False
    drop_param_replies: int = 0  # the next N PARAM_VALUE are lost on the way out
    duplicate_param_replies: bool = False  # every PARAM_VALUE is sent twice
