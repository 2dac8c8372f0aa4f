"""A dataset's joints in the model's convention: the edge where data of a coupled robot (its controller's
readings, hil.geometry.coupling) becomes the kinematic joints every analysis works in."""

from __future__ import annotations

import numpy as np
import pandas as pd

from hil.data.dataset import DatasetError, joint_columns
from hil.geometry.coupling import JointConvention, JointCoupling


def joints_to_kinematic(
    df: pd.DataFrame,
    coupling: JointCoupling | None,
    convention: JointConvention | str | None,
    source: str,
) -> pd.DataFrame:
    """A dataset's joints as the model's: converted from the controller's when it says so. Data of a coupled
    robot that does not say which convention it holds is refused with the choice named (never silently
    read one way); a robot without coupling reads either convention unchanged. A campaign's recorded
    convention (`attrs["joint_convention"]`, from its session's snapshot) stands for the option. The frame
    returned says "kinematic" there (a second call converts nothing) and `attrs["joints_read_as"]` what
    the data held."""
    if coupling is None or not coupling.coupled_rows():
        return df
    recorded = df.attrs.get("joint_convention")  # a campaign records what its session read
    if convention is not None and recorded is not None and JointConvention(convention) != recorded:
        raise DatasetError(
            f"{source}: --joint-convention {convention}, but the campaign recorded its joints as the "
            f"{recorded} joints; drop --joint-convention (the campaign says it)"
        )
    convention = convention if convention is not None else recorded
    if convention is None:
        raise DatasetError(
            f"{source}: this robot couples its joints ({coupling.describe()}); say which joints the data holds: "
            "--joint-convention controller (as the controller and pendant report them) or --joint-convention "
            "kinematic (already converted)"
        )
    convention = JointConvention(convention)
    out = df.copy()
    out.attrs = {
        **df.attrs,
        "joint_convention": str(JointConvention.KINEMATIC),
        "joints_read_as": str(convention),
    }
    if convention is JointConvention.CONTROLLER:
        cols = joint_columns(coupling.n_joints)
        q = out[cols].to_numpy(float)
        for limit in coupling.limits:
            v = q @ limit.coefficients
            beyond = np.flatnonzero((v < limit.lower_rad) | (v > limit.upper_rad))
            if beyond.size:
                raise DatasetError(
                    f"{source}: row {beyond[0] + 1} breaks the robot's joint interaction limit "
                    f"{limit.describe()} ({beyond.size} row(s) do); are these the controller's joints? if they "
                    "are already kinematic, give --joint-convention kinematic"
                )
        out[cols] = coupling.to_kinematic(q)
    return out
