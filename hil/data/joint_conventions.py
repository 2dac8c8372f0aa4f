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
    read one way); a robot without coupling reads either convention unchanged. `attrs["joint_convention"]`
    records where the joints came from."""
    if coupling is None or not coupling.coupled_rows():
        return df
    if convention is None:
        raise DatasetError(
            f"{source}: this robot couples its joints ({coupling.describe()}); say which joints the data holds: "
            "--joint-convention controller (as the controller and pendant report them) or --joint-convention "
            "kinematic (already converted)"
        )
    convention = JointConvention(convention)
    out = df.copy()
    out.attrs = dict(df.attrs)
    out.attrs["joint_convention"] = str(convention)
    if convention is JointConvention.CONTROLLER:
        cols = joint_columns(coupling.n_joints)
        q = out[cols].to_numpy(float)
        outside = np.flatnonzero(~coupling.within_limits(q))
        if outside.size:
            bad = next(lim for lim in coupling.limits if not lim.coefficients @ q[outside[0]] <= lim.upper_rad
                       or not lim.coefficients @ q[outside[0]] >= lim.lower_rad)  # fmt: skip
            raise DatasetError(
                f"{source}: row {outside[0] + 1} breaks the robot's joint interaction limit {bad.describe()} "
                f"({outside.size} row(s) do); are these the controller's joints? if they are already kinematic, "
                "give --joint-convention kinematic"
            )
        out[cols] = coupling.to_kinematic(q)
    return out
