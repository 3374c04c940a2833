"""What the simulated airframe's battery reports: SYS_STATUS and BATTERY_STATUS. No I/O, no
clock.

The battery is a 6S Li-ion pack drawn at the profile's constant power: 4.2 V a cell full,
3.3 V empty, linear in between.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mav

if TYPE_CHECKING:
    from gateway.sim.airframe import SimProfile

__all__ = ["power_messages"]

_CELLS = 6  # 6S Li-ion: 4.2 V full, 3.3 V empty, linear in between
_CELL_FULL_V, _CELL_EMPTY_V = 4.2, 3.3
_UINT16_MAX = 0xFFFF
# The sensors SYS_STATUS reports as present, enabled and healthy.
_SENSORS = (
    mav.MAV_SYS_STATUS_SENSOR_3D_GYRO | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mav.MAV_SYS_STATUS_SENSOR_3D_MAG | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mav.MAV_SYS_STATUS_SENSOR_DIFFERENTIAL_PRESSURE | mav.MAV_SYS_STATUS_SENSOR_GPS
    | mav.MAV_SYS_STATUS_SENSOR_BATTERY
)  # fmt: skip


def power_messages(encoder: Any, p: SimProfile, t_s: float) -> list[Any]:
    """SYS_STATUS and BATTERY_STATUS at sim time ``t_s`` (seconds of flight at ``power_w``)."""
    used_wh = min(p.power_w * t_s / 3600.0, p.battery_wh)
    soc = 1.0 - used_wh / p.battery_wh
    cell_v = _CELL_EMPTY_V + (_CELL_FULL_V - _CELL_EMPTY_V) * soc
    current_ca = round(p.power_w / (_CELLS * cell_v) * 100) if soc > 0 else 0
    # Charge drawn at constant power from a voltage linear in state of charge, in closed
    # form: Q = ∫ E dsoc / V(soc) = E / ΔV · ln(V_full / V).
    delta_v = _CELLS * (_CELL_FULL_V - _CELL_EMPTY_V)
    used_mah = round(p.battery_wh / delta_v * math.log(_CELL_FULL_V / cell_v) * 1000)
    remaining = round(100 * soc)
    low = remaining <= 20
    charge_state = mav.MAV_BATTERY_CHARGE_STATE_LOW if low else mav.MAV_BATTERY_CHARGE_STATE_OK
    status = encoder.sys_status_encode(
        _SENSORS, _SENSORS, _SENSORS, 300, round(_CELLS * cell_v * 1000), current_ca,
        remaining, 0, 0, 0, 0, 0, 0,
    )  # fmt: skip
    battery = encoder.battery_status_encode(
        0, mav.MAV_BATTERY_FUNCTION_ALL, mav.MAV_BATTERY_TYPE_LION, 2500,
        [round(cell_v * 1000)] * _CELLS + [_UINT16_MAX] * (10 - _CELLS),
        current_ca, used_mah, round(used_wh * 36), remaining,
        time_remaining=round((p.battery_wh - used_wh) / p.power_w * 3600),
        charge_state=charge_state,
    )  # fmt: skip
    return [status, battery]
