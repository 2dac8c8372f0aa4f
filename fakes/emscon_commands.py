"""The fake emScon tracker's command set: one handler per TPI command, answering from the shared state.

`handle` decodes a command packet and calls `_cmd_<command name>`; a handler returns the (status, values...)
of a plain answer, or None when it sent its answers itself. Set* commands are followed by their "...Changed"
event to every client; commands the fake does not implement answer NotImplemented.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable

import numpy as np

from drivers import emscon_codec as codec
from drivers.emscon_codec import Command, CoordinateSystem, Status, StatusChange, WeatherMonitorStatus
from fakes.emscon_measure import Beam
from fakes.emscon_state import Client, valid_unit

log = logging.getLogger("fakes.emscon_server")


class CommandSet:
    """The handlers of the TPI commands the fake knows; `broadcast` sends an event to every client."""

    def __init__(self, beam: Beam, broadcast: Callable[..., None]):
        self.beam = beam
        self.broadcast = broadcast
        self.cell = beam.cell
        self.config = beam.config
        self.state = beam.state

    async def handle(self, session: Client, packet: bytes, command: int) -> None:
        """Answer one command packet on `session` (unsolicited events go to every client)."""
        try:
            known = Command(command)
        except ValueError:
            session.send(codec.pack_answer(command, Status.NOT_IMPLEMENTED))
            return
        self.state.command_counts[known.name] += 1
        try:
            cmd = codec.decode_client_packet(packet)
        except codec.CodecError:
            session.send(codec.pack_answer(command, Status.WRONG_PARAMETER))
            return
        self.beam.track()
        handler = getattr(self, f"_cmd_{known.name.lower()}", None)
        if handler is None:
            session.send(codec.pack_answer(command, Status.NOT_IMPLEMENTED))
            return
        result = handler(session, *cmd.params)
        if asyncio.iscoroutine(result):
            result = await result
        if result is not None:  # (status, values...) of a plain answer
            session.send(codec.pack_answer(command, *result))

    def _cmd_exit_application(self, session):
        self.state.exit_requests += 1
        log.error("fake tracker: a client sent ExitApplication (would stop a real emScon server)")
        return (Status.NOT_IMPLEMENTED,)

    def _cmd_get_system_status(self, session):
        st, cfg = self.state, self.config
        tps = (
            codec.TrackerProcessorStatus.INITIALIZED
            if st.initialized
            else codec.TrackerProcessorStatus.COMPENSATION_SET
        )
        laser = codec.LaserStatus.LASER_READY if st.laser_on else codec.LaserStatus.LASER_OFF
        return (0, st.last_result_status, tps, laser, 2, *cfg.version, st.settings[0], 0, cfg.serial_number)

    def _cmd_get_tracker_status(self, session):
        if self.state.measuring:
            return (0, codec.TrackerStatus.BUSY)
        ready = self.state.initialized and self.beam.ready()
        return (0, codec.TrackerStatus.READY if ready else codec.TrackerStatus.NOT_READY)

    def _cmd_get_measurement_status_info(self, session):
        st = self.state
        info = 1 | 2 | 4 | 8 | 4096
        if st.initialized:
            info |= codec.MSI_INITIALIZED
        if self.beam.ready():
            info |= codec.MSI_REFLECTOR_FOUND
        return (0, st.last_result_status, info)

    def _changed(self, session, change: StatusChange, command: int):
        session.send(codec.pack_answer(command, Status.ALL_OK))
        self.broadcast(codec.pack_status_change(change))

    def _cmd_set_units(self, session, *values):
        try:
            self.state.units = codec.Units.from_tuple(values)
        except ValueError:
            bad = next(i for i in range(5) if not valid_unit(i, values[i]))
            return (Status.WRONG_PARAMETER1 + bad,)
        self._changed(session, StatusChange.UNITS_CHANGED, Command.SET_UNITS)

    def _cmd_get_units(self, session):
        return (0, *self.state.units.as_tuple())

    async def _cmd_initialize(self, session):
        await asyncio.sleep(self.config.init_delay_s)
        self.state.initialized = True
        session.send(codec.pack_answer(Command.INITIALIZE, Status.ALL_OK))
        self.broadcast(codec.pack_status_change(StatusChange.INITIALIZATION_STATUS_CHANGED))
        if self.beam.ready():
            self.broadcast(codec.pack_status_change(StatusChange.MEAS_STATUS_READY))

    def _cmd_set_measurement_mode(self, session, mode):
        continuous = mode == codec.MeasMode.CONTINUOUS_TIME and self.config.continuous_modes
        if mode != codec.MeasMode.STATIONARY and not continuous:
            return (Status.NOT_IMPLEMENTED,)
        self.state.meas_mode = mode
        self._changed(session, StatusChange.MEASUREMENT_MODE_CHANGED, Command.SET_MEASUREMENT_MODE)

    def _cmd_get_measurement_mode(self, session):
        return (0, self.state.meas_mode)

    def _cmd_set_continuous_time_mode_params(self, session, separation_ms, points, use_region, region_type):
        if not self.config.continuous_modes:
            return (Status.NOT_IMPLEMENTED,)
        if separation_ms < self.config.min_time_separation_ms or points < 0:
            return (Status.WRONG_PARAMETER,)
        if use_region:  # measurement regions (box, sphere) are not modelled
            return (Status.NOT_IMPLEMENTED,)
        self.state.continuous_time = (separation_ms, points, use_region, region_type)
        self._changed(
            session, StatusChange.CONTINUOUS_TIME_MODE_PARAMS_CHANGED, Command.SET_CONTINUOUS_TIME_MODE_PARAMS
        )

    def _cmd_get_continuous_time_mode_params(self, session):
        if not self.config.continuous_modes:
            return (Status.NOT_IMPLEMENTED,)
        return (0, *self.state.continuous_time)

    def _cmd_set_stationary_mode_params(self, session, meas_time_ms, use_adm):
        if not 1 <= meas_time_ms <= 3_600_000:
            return (Status.PARAMETER1_OUT_OF_RANGE_NOK,)
        self.state.meas_time_ms, self.state.use_adm = meas_time_ms, bool(use_adm)
        self._changed(
            session, StatusChange.STATIONARY_MODE_PARAMS_CHANGED, Command.SET_STATIONARY_MODE_PARAMS
        )

    def _cmd_get_stationary_mode_params(self, session):
        return (0, self.state.meas_time_ms, int(self.state.use_adm))

    def _cmd_set_coordinate_system_type(self, session, cs):
        if cs not in codec.SUPPORTED_SYSTEMS:
            return (Status.NOT_IMPLEMENTED,)
        self.state.cs = CoordinateSystem(cs)
        self._changed(
            session, StatusChange.COORDINATE_SYSTEM_TYPE_CHANGED, Command.SET_COORDINATE_SYSTEM_TYPE
        )

    def _cmd_get_coordinate_system_type(self, session):
        return (0, self.state.cs)

    def _cmd_set_system_settings(self, session, *settings):
        if settings[0] not in (0, 1, 2):
            return (Status.WRONG_PARAMETER1,)
        if settings[0] != WeatherMonitorStatus.NOT_CONNECTED and not self.config.weather_monitor:
            return (Status.NO_WEATHERMONITOR_FOUND,)
        self.state.settings = [int(v) for v in settings]
        self._changed(session, StatusChange.SYSTEM_SETTINGS_CHANGED, Command.SET_SYSTEM_SETTINGS)

    def _cmd_get_system_settings(self, session):
        return (0, *self.state.settings)

    def _cmd_set_statistic_mode(self, session, stationary, continuous):
        if stationary not in (0, 1) or continuous not in (0, 1):
            return (Status.WRONG_PARAMETER,)
        self.state.statistic_mode = (stationary, continuous)
        self._changed(session, StatusChange.STATISTIC_MODE_CHANGED, Command.SET_STATISTIC_MODE)

    def _cmd_get_statistic_mode(self, session):
        return (0, *self.state.statistic_mode)

    def _cmd_get_reflectors(self, session):
        refl = self.config.reflectors
        u = self.state.units
        session.send(
            *(
                codec.pack_answer(
                    Command.GET_REFLECTORS, 0, len(refl), r.id, r.target_type,
                    u.length_to_wire(r.surface_offset_m), codec.encode_name(r.name),
                )
                for r in refl
            )
        )  # fmt: skip

    def _cmd_set_reflector(self, session, reflector_id):
        if reflector_id not in {r.id for r in self.config.reflectors}:
            return (Status.WRONG_PARAMETER1,)
        self.state.reflector_id = reflector_id
        self._changed(session, StatusChange.REFLECTOR_CHANGED, Command.SET_REFLECTOR)

    def _cmd_get_reflector(self, session):
        return (0, self.state.reflector_id)

    def _cmd_set_environment_params(self, session, t, p, h):
        u, cfg = self.state.units, self.config
        t_c, p_hpa = u.temperature_from_wire(t), u.pressure_from_wire(p)
        ranges = (cfg.temperature_range_c, cfg.pressure_range_hpa, cfg.humidity_range_pct)
        if not all(lo <= v <= hi for v, (lo, hi) in zip((t_c, p_hpa, h), ranges, strict=True)):
            return (Status.METEO_DATA_OUT_OF_RANGE,)
        self.state.manual_meteo = (t_c, p_hpa, h)
        self._changed(session, StatusChange.ENVIRONMENT_PARAMS_CHANGED, Command.SET_ENVIRONMENT_PARAMS)

    def _cmd_get_environment_params(self, session):
        return (0, *self.beam.meteo_wire())

    def _cmd_set_search_params(self, session, radius, timeout_ms):
        radius_m = self.state.units.length_from_wire(radius)
        if not radius_m > 0 or timeout_ms < 0:
            return (Status.WRONG_PARAMETER1 if not radius_m > 0 else Status.WRONG_PARAMETER2,)
        self.state.search_radius_m, self.state.search_timeout_ms = radius_m, timeout_ms
        self._changed(session, StatusChange.SEARCH_PARAMS_CHANGED, Command.SET_SEARCH_PARAMS)

    def _cmd_get_search_params(self, session):
        return (0, self.state.units.length_to_wire(self.state.search_radius_m), self.state.search_timeout_ms)

    def _cmd_stop_measurement(self, session):
        self.beam.stop_stream()
        return (0,)

    def _wire_point(self, v1, v2, v3, spherical: bool) -> np.ndarray:
        """A point from the wire: in the current CS, or (HVD commands) always as Hz, V, D.

        HVD angles follow the current spherical convention when one is selected, else SCC (an assumption).
        """
        cs = self.state.cs
        if spherical and cs not in codec.SPHERICAL_SYSTEMS:
            cs = CoordinateSystem.SCC
        return codec.wire_to_cartesian(np.array([v1, v2, v3]), cs, self.state.units)

    async def _go(self, session, command: int, p_aim_m: np.ndarray, lock: bool) -> None:
        if not self.state.initialized:
            session.send(codec.pack_answer(command, Status.TRACKER_NOT_INITIALIZED))
            return
        if not np.all(np.isfinite(p_aim_m)):
            session.send(codec.pack_answer(command, Status.WRONG_PARAMETER))
            return
        await asyncio.sleep(self.config.motion_delay_s)
        if lock:
            self.beam.acquire(p_aim_m)
        else:
            self.state.direction = p_aim_m / max(float(np.linalg.norm(p_aim_m)), 1e-9)
            if self.state.locked_smr is not None:
                self.beam.lose_lock()
        session.send(codec.pack_answer(command, Status.ALL_OK))

    async def _cmd_go_position(self, session, v1, v2, v3, use_adm):
        await self._go(session, Command.GO_POSITION, self._wire_point(v1, v2, v3, False), True)

    async def _cmd_go_position_hvd(self, session, hz, vt, d, use_adm):
        await self._go(session, Command.GO_POSITION_HVD, self._wire_point(hz, vt, d, True), True)

    async def _cmd_point_laser(self, session, v1, v2, v3):
        await self._go(session, Command.POINT_LASER, self._wire_point(v1, v2, v3, False), False)

    async def _cmd_point_laser_hvd(self, session, hz, vt, d):
        await self._go(session, Command.POINT_LASER_HVD, self._wire_point(hz, vt, d, True), False)

    async def _cmd_find_reflector(self, session, approx_distance):
        if not self.state.initialized:
            return (Status.TRACKER_NOT_INITIALIZED,)
        distance_m = self.state.units.length_from_wire(approx_distance)
        if not distance_m > 0:
            return (Status.WRONG_PARAMETER1,)
        await asyncio.sleep(self.config.motion_delay_s)
        if not self.beam.acquire(self.state.direction * distance_m):
            return (self.config.no_target_status,)
        return (0,)

    async def _cmd_start_measurement(self, session):
        return await self.beam.measure(session)

    def _cmd_get_direction(self, session):
        cs = CoordinateSystem.SCW if self.state.cs == CoordinateSystem.SCW else CoordinateSystem.SCC
        hz, v, _ = codec.cartesian_to_wire(self.state.direction, cs, self.state.units)
        return (0, hz, v)

    # ---- the rest of the fact sheet's command subset ------------------------------------------------------
    def _cmd_set_temperature_range(self, session, value):
        if value not in (0, 1, 2, 3):
            return (Status.WRONG_PARAMETER1,)
        self.state.temperature_range = value
        self._changed(session, StatusChange.TEMPERATURE_RANGE_CHANGED, Command.SET_TEMPERATURE_RANGE)

    def _cmd_get_temperature_range(self, session):
        return (0, self.state.temperature_range)

    def _cmd_switch_laser(self, session, on):
        self.state.laser_on = bool(on)
        if not on:
            self.beam.lose_lock()
        return (0,)

    def _cmd_set_station_orientation_params(self, session, *values):
        if any(values):  # the fake reports raw tracker-frame results only
            return (Status.NOT_IMPLEMENTED,)
        self.state.station_orientation = values
        self._changed(
            session, StatusChange.STATION_ORIENTATION_PARAMS_CHANGED, Command.SET_STATION_ORIENTATION_PARAMS
        )

    def _cmd_get_station_orientation_params(self, session):
        return (0, *self.state.station_orientation)

    def _cmd_set_transformation_params(self, session, *values):
        if any(values[:6]) or values[6] != 1.0:  # identity only, as above
            return (Status.NOT_IMPLEMENTED,)
        self.state.transformation = values
        self._changed(session, StatusChange.TRANSFORMATION_PARAMS_CHANGED, Command.SET_TRANSFORMATION_PARAMS)

    def _cmd_get_transformation_params(self, session):
        return (0, *self.state.transformation)

    def _cmd_set_refraction_params(self, session, ifm, adm):
        if not (1.0 <= ifm < 1.001 and 1.0 <= adm < 1.001):
            return (Status.WRONG_PARAMETER1 if not 1.0 <= ifm < 1.001 else Status.WRONG_PARAMETER2,)
        self.state.refraction = (ifm, adm)
        self._changed(session, StatusChange.REFRACTION_PARAMS_CHANGED, Command.SET_REFRACTION_PARAMS)

    def _cmd_get_refraction_params(self, session):
        return (0, *self.state.refraction)

    def _cmd_change_face(self, session):
        if not self.state.initialized:
            return (Status.TRACKER_NOT_INITIALIZED,)
        self.state.face = 2 if self.state.face == 1 else 1
        face_event = StatusChange.IS_FACE1 if self.state.face == 1 else StatusChange.IS_FACE2
        self._changed(session, face_event, Command.CHANGE_FACE)

    def _cmd_get_face(self, session):
        return (0, self.state.face)

    async def _cmd_go_bird_bath(self, session):
        await self._go(session, Command.GO_BIRD_BATH, np.array(self.config.birdbath_point_m), True)

    async def _cmd_go_bird_bath2(self, session, clockwise):
        await self._go(session, Command.GO_BIRD_BATH2, np.array(self.config.birdbath_point_m), True)

    def _cmd_get_tp_info(self, session):
        # boot, TP firmware and LCP firmware versions, processor type ATC900 (6), uP type, clock, sensor type
        return (0, 1, 0, 3, 2, 2, 1, 6, 0, 0, codec.LTS_AT901_LR)

    def _cmd_set_long_system_parameter(self, session, param, value):
        if param == codec.SP_TCP_COMMAND_QUEUE_SIZE and value != 0:
            return (Status.NOT_IMPLEMENTED,)  # the fake keeps the queue off: one command at a time
        self.state.long_params[param] = value
        return (0,)

    def _cmd_get_long_system_parameter(self, session, param):
        return (0, param, self.state.long_params.get(param, 0))

    def _cmd_set_double_system_parameter(self, session, param, value):
        self.state.double_params[param] = value
        return (0,)

    def _cmd_get_double_system_parameter(self, session, param):
        return (0, param, self.state.double_params.get(param, 0.0))

    def _cmd_get_object_temperature(self, session):
        if not self.config.object_probe:
            return (self.config.no_object_probe_status,)
        return (0, self.state.units.temperature_to_wire(float(self.cell.structure_temperature_c())))

    def _cmd_clear_command_queue(self, session, which):
        return (0,) if which in (0, 1) else (Status.WRONG_PARAMETER1,)

    def _cmd_get_current_prism_position(self, session):
        if not self.beam.ready():
            return (self.config.no_target_status,)
        st = self.state
        return (0, *codec.cartesian_to_wire(st.lock_p_m, st.cs, st.units))

    def _cmd_get_tracker_info(self, session):
        cfg, u = self.config, self.state.units
        return (
            0, codec.LTS_AT901_LR, codec.encode_name(cfg.tracker_name), cfg.serial_number, 1, 1, 1, 1,
            0.0, u.length_to_wire(cfg.max_distance_m), u.length_to_wire(cfg.min_distance_m), 1000, 2,
            u.angle_to_wire(2 * math.pi), u.angle_to_wire(math.radians(145.0)), 0, 1, 0,
        )  # fmt: skip

    def _cmd_get_system_software_version(self, session):
        return (0, codec.encode_name(".".join(map(str, self.config.version))))
