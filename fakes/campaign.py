"""Visit planned joints on the simulated cell and return what the tracker measured, in the dataset contract.

Planning the joints is the planners' job (hil.runner.planners, as the procedures do); visiting them on the
simulated cell, as a real cell would, is the fake's. At each pose one SMR is read, or several (SMRs seated
in tool nests, read in turn while the robot stands still: one row each, same joints and time), and
optionally a 6-DoF probe's orientation (T-Mac style) with angular noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from fakes.cell import SimulatedCell, SmrLocation
from hil.data.dataset import make_dataset


@dataclass(frozen=True)
class Probe:
    """A 6-DoF probe on the tool: its true frame in the flange and the noise of its orientation reading."""

    R_flange_probe: np.ndarray = field(default_factory=lambda: np.eye(3))
    angle_sigma_rad: float = float(np.deg2rad(0.01))  # 1 sigma per axis

    @classmethod
    def drawn(cls, seed: int, error_sigma_rad: float = float(np.deg2rad(0.3)), **kw: float) -> Probe:
        """A probe mounted with a hidden misalignment (rotation vector, `error_sigma_rad` per axis)."""
        rv = np.random.default_rng([seed, 6]).normal(0.0, error_sigma_rad, 3)
        return cls(Rotation.from_rotvec(rv).as_matrix(), **kw)


def simulate_campaign(
    cell: SimulatedCell,
    q_cmd: np.ndarray,
    smr_id: int = 1,
    seconds_per_point: float = 4.0,
    nests: Sequence[int] | None = None,
    probe: Probe | None = None,
) -> pd.DataFrame:
    """Visit q_cmd (N, 6) in order on the cell and return the rows of the dataset contract.

    `nests`: seat SMR k in tool nest k for every k given and read each of them at every pose (rows pose by
    pose, `smr` = nest); default: SMR `smr_id` where it sits. `probe`: every row also carries the probe's
    orientation (rx_deg, ry_deg, rz_deg, default convention) read with its angular noise.

    Every row records `air_temperature_c` as a campaign export does (hil.data.store): the air temperature the
    tracker's refraction used at that point, its weather station's reading of the hall's air, or the fixed
    value a stuck station (or a hand entry) gives (`SimulatedCell.station_air_c`).
    """
    if nests is None:
        smrs = [smr_id]
    else:
        smrs = list(nests)
        for k in smrs:
            cell.place_smr(k, SmrLocation("nest", index=k))
    r = cell.run_sequence(q_cmd, smr_id=smrs[0], seconds_per_point=seconds_per_point)
    T_tracker_flange = cell.T_tracker_base @ r["T_base_flange_true"]
    N = len(r["t_s"])
    p_meas = [r["p_tracker_measured"]]
    for k in smrs[1:]:
        p_flange = cell.smr_point_flange(cell.smr_location(k))
        if p_flange is None:
            raise ValueError(f"SMR {k} is fixed in the room; seat it on the robot")
        p_true = T_tracker_flange[:, :3, :3] @ p_flange + T_tracker_flange[:, :3, 3]
        p_meas.append(cell.tracker_reading(k, p_true, r["t_s"]))
    ids = [loc.number if loc.kind == "nest" else 0 for loc in map(cell.smr_location, smrs)]
    order = np.arange(N * len(smrs)).reshape(len(smrs), N).T.ravel()  # pose by pose, nests in turn
    R_probe = None
    if probe is not None:
        rng = np.random.default_rng([cell.config.seed, 5, int(cell.time_s)])
        R_true = T_tracker_flange[:, :3, :3] @ probe.R_flange_probe
        R_probe = np.concatenate(
            [
                Rotation.from_rotvec(rng.normal(0.0, probe.angle_sigma_rad, (N, 3))).as_matrix() @ R_true
                for _ in smrs
            ]
        )[order]
    rep = len(smrs)
    air_c = cell.station_air_c(r["t_s"])
    df = make_dataset(
        np.tile(r["q_encoder"], (rep, 1))[order],
        np.concatenate(p_meas)[order],
        t_s=np.tile(r["t_s"], rep)[order],
        temperature_c=np.tile(r["temperature_c"], rep)[order],
        smr=np.repeat(ids, N)[order],
        R_tracker_probe=R_probe,
    )
    df["air_temperature_c"] = np.tile(air_c, rep)[order]
    return df
