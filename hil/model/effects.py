"""Candidate effects a geometric model lacks, each a small parametric model with its own regressors.

Every family is written from its physics, independently of any simulator:

- ``gravity_compliance`` (joint j): the joint yields in proportion to the gravity torque about its
  axis. The torque is a mass-weighted sum of lever arms ``z_j . ((p_k - o_j) x e_z)`` of the points
  downstream of the joint. When the robot file gives every link's mass (`KinematicModel.link_masses_kg`)
  the torque is computed from them (each link's mass at the middle of its span between two frame origins,
  a recorded payload at the tool point) and the joint's compliance (rad per N m) is its ONE coefficient;
  the term is then physics, not a candidate (`gravity_physics`): every joint that carries a torque has it,
  fitted with a prior (`GRAVITY_PRIOR_DEFLECTION_RAD`). Without masses the downstream frame origins' and the
  tool point's lever arms span the torque (lumped motor masses sit at origins, a uniform link's centre of
  mass between two): the unknown masses and the stiffness merge into one coefficient per lever arm, the
  arms the data cannot tell apart merged by an SVD at fit time, and the term is a candidate. That free form
  fits the sampled poses as well but extrapolates worse: trained on one public UR10 campaign (series B or
  C, whose joint ranges do not overlap) and validated on the other, it left 0.80 / 0.80 mm where one
  compliance per joint left 0.61 / 0.71 mm.
- ``cyclic`` (joint j): 1st and 2nd harmonic of the joint angle (gear eccentricity, encoder mounting),
  each only where the sampled range covers most of its period (`CYCLIC_MIN_PERIODS`).
- ``backlash`` (joint j): half the gap times the sign of the joint's approach direction (row order).
- ``joint_scale`` (joint j): the joint turns (1 + s) times what its encoder says (a transmission ratio
  or encoder scale error), i.e. an offset ``s * q``.
- ``thermal_expansion``: every link length (a, d) grows by ``k * dT``; the tool does not. When the robot file
  gives the links' material (`KinematicModel.expansion_per_k`) and the campaign records a temperature, the
  term is physics, not a candidate (`material_expansion`): it enters the model with a Gaussian prior centred
  on the material's coefficient (`Effect.prior`), so a campaign spanning little temperature keeps about the
  material's value (the growth is assumed) and one spanning a lot follows the data: where they contradict
  the material the prior is dropped (`without_prior`), where they find no growth it is held at zero
  (`hold_absent`; hil.analysis.diagnosis.physics_terms decides).
- ``thermal_drift``: the tracker sees the base translate by ``v * dT`` (floor, stand or tracker drift).
- ``tracker_scale``: the tracker's distances scale by ``1 + s * dT`` about the tracker itself: the refractive
  index of the air it computes from a wrong air temperature (a manual setting while the hall warms, a weather
  station in the sun) is off by about 1 ppm per K. It rivals the links' growth, which is centred on the base
  and along the links: the tracker's scale also stretches the base-to-tracker distance and the tool.

Thermal families take the structure temperature when the dataset records one that varies, else the
time since the campaign started. Joint effects are output-side joint offsets added to the reported
joints before the forward kinematics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd

from hil.data.jsonable import to_jsonable
from hil.geometry.kinematics import (
    KinematicModel,
    chain_axes,
    flange_poses_and_last_origins,
    last_link_origins,
    points_on_flanges,
)

# Names used in reports and model files (the documented vocabulary).
EFFECT_FAMILIES: tuple[str, ...] = (
    "gravity_compliance",
    "cyclic",
    "backlash",
    "joint_scale",
    "thermal_expansion",
    "thermal_drift",
    "tracker_scale",
)

GRAVITY_DIRECTION_BASE = np.array([0.0, 0.0, -1.0])  # the robot stands upright: base z points up
STANDARD_GRAVITY_M_S2 = 9.80665

# Largest plausible half swing of the joint offset a joint effect adds (industrial arms, harmonic drives
# and RV gears): beyond it the fitted "effect" stands in for something else (geometry, units, robot model).
PLAUSIBLE_SWING_RAD: dict[str, float] = {
    "gravity_compliance": np.deg2rad(0.3),
    "cyclic": np.deg2rad(0.1),
    "backlash": np.deg2rad(0.1),
    "joint_scale": np.deg2rad(0.3),
}
PLAUSIBLE_EXPANSION_PER_K = 100e-6  # aluminium 23, steel 12, a carbon tube ~0 ppm/K
PLAUSIBLE_DRIFT_M = 2e-3  # largest base drift over one campaign
# Refraction: n - 1 of air falls ~0.93 ppm per K, so a tracker computing it from an air temperature off by
# dT measures distances (1 - 0.93e-6 dT) long. A scale beyond 5 ppm per K of the recorded temperature (or 50
# ppm over a campaign) is no refraction error.
REFRACTION_PER_K = -0.93e-6
PLAUSIBLE_TRACKER_SCALE_PER_K = 5e-6
PLAUSIBLE_TRACKER_SCALE = 50e-6

# Near-ties between candidates go to the more physically expected family (lower rank first).
PHYSICAL_RANK: dict[str, int] = {
    "gravity_compliance": 0,
    "thermal_expansion": 1,
    "backlash": 2,
    "cyclic": 3,
    "thermal_drift": 4,
    "tracker_scale": 5,
    "joint_scale": 6,
}


@dataclass
class EffectContext:
    """Everything an effect's regressors may depend on, row for row with a dataset."""

    q: np.ndarray  # (N, n) reported joints, rad
    t_s: np.ndarray | None = None
    temperature_c: np.ndarray | None = None
    payload_kg: np.ndarray | None = None
    p_flange_tool: np.ndarray | None = None  # (N, 3) tool point per row, m (for lever arms)
    approach: np.ndarray | None = None  # (N, n) approach signs from the full row order (see approach_signs)
    cache: dict = field(default_factory=dict, repr=False)  # regressors per effect, row for row

    @property
    def n(self) -> int:
        return self.q.shape[0]

    @classmethod
    def from_frame(cls, df: pd.DataFrame, q: np.ndarray) -> EffectContext:
        """Pick the optional driver columns out of a dataset frame."""

        def col(name: str) -> np.ndarray | None:
            return df[name].to_numpy(float) if name in df.columns else None

        return cls(
            q=q,
            t_s=col("t_s"),
            temperature_c=col("temperature_c"),
            payload_kg=col("payload_kg"),
            approach=approach_signs(q),
        )

    def subset(self, rows: np.ndarray) -> EffectContext:
        """The context restricted to some rows (for k-fold splits)."""

        def take(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else x[rows]

        return EffectContext(
            q=self.q[rows],
            t_s=take(self.t_s),
            temperature_c=take(self.temperature_c),
            payload_kg=take(self.payload_kg),
            p_flange_tool=take(self.p_flange_tool),
            approach=take(self.approach),
            cache={k: v[rows] for k, v in self.cache.items()},
        )


@dataclass
class Effect:
    """One effect instance: a family, an optional 1-based joint, its parameters and fitted state."""

    family: ClassVar[str] = ""
    # "joint" (joint offset), "growth" (link lengths), "offset" (tracker frame), "scale" (about the tracker)
    kind: ClassVar[str] = "joint"
    joint: int | None = None
    params: np.ndarray = field(default_factory=lambda: np.zeros(0))
    state: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        return self.family if self.joint is None else f"{self.family}_j{self.joint}"

    @property
    def joint_index(self) -> int:
        """0-based column of the joint a joint effect acts on (`joint` counts from 1)."""
        if self.joint is None:
            raise ValueError(f"the effect {self.label} names no joint")
        return self.joint - 1

    @property
    def param_names(self) -> list[str]:
        return [f"{self.label}.{nm}" for nm in self.coefficient_names()]

    def coefficient_names(self) -> list[str]:
        raise NotImplementedError

    def coefficient_unit(self) -> str:
        """The SI unit of every coefficient: what the effect is in (rad for a joint offset, 1 for a growth
        factor, m for a tracker offset) per unit of its regressor."""
        raise NotImplementedError

    def prepare(self, ctx: EffectContext, nominal: KinematicModel) -> bool:
        """Fix the data-dependent state from training data; False when the data cannot show the effect."""
        self.params = np.zeros(len(self.coefficient_names()))
        return True

    def regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        """(N, k) regressors: the effect is ``regressors @ params`` (joint offset, growth or offset factor)."""
        raise NotImplementedError

    def cached_regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        """`regressors`, memoised in the context (tool points rounded to 0.1 mm: lever arms do not care)."""
        tools = ctx.p_flange_tool
        if tools is None:
            tool: object = b""
        elif tools.ndim == 2 and tools.strides[0] == 0:  # one tool point broadcast to every row
            tool = ("every row", len(tools), np.round(tools[0] * 1e4).astype(np.int64).tobytes())
        else:
            tool = np.round(tools * 1e4).astype(np.int64).tobytes()
        drivers = (
            self.state.get("mix"),
            self.state.get("masses_kg"),
            self.state.get("driver"),
            self.state.get("harmonics"),
        )
        key = (self.label, repr(drivers), hash(tool))
        if key not in ctx.cache:
            ctx.cache[key] = self.regressors(ctx, nominal)
        return ctx.cache[key]

    def driver(self, ctx: EffectContext, nominal: KinematicModel) -> tuple[str, np.ndarray]:
        """The physical quantity to plot residuals against: (label with unit, (N,) values)."""
        raise NotImplementedError

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        """Physically meaningful figures of the fitted effect (for reports)."""
        return {}

    def implausible(self, ctx: EffectContext, nominal: KinematicModel) -> str | None:
        """Why the fitted size is physically implausible on these rows (None when it is plausible)."""
        limit = PLAUSIBLE_SWING_RAD.get(self.family)
        if self.kind != "joint" or limit is None:
            return None
        offset = self.regressors(ctx, nominal) @ self.params
        swing = float(np.ptp(offset)) / 2
        if swing <= limit:
            return None
        return (
            f"implausible size: it swings joint {self.joint} by +-{np.rad2deg(swing):.3g} deg (a real "
            f"{self.family.replace('_', ' ')} stays below {np.rad2deg(limit):.2g} deg); it is fitting something else"
        )

    def prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Gaussian prior on the coefficients, (mean, std) each (k,) in their SI unit; None without one (the
        coefficients are then free, up to the solver's small ridge)."""
        return None

    @property
    def held(self) -> bool:
        """Coefficients held at their values: no fit moves them (the model's Jacobian gives them no column)."""
        return bool(self.state.get("held", False))

    def to_dict(self) -> dict:
        return {
            "family": self.family,
            "joint": self.joint,
            "params": [float(v) for v in self.params],
            "param_names": self.param_names,
            "state": to_jsonable(self.state),
        }


class GravityCompliance(Effect):
    family = "gravity_compliance"

    @property
    def from_masses(self) -> bool:
        """The torque form: one compliance, the torque computed from the robot's link masses."""
        return "masses_kg" in self.state

    def coefficient_names(self) -> list[str]:
        if self.from_masses:
            return ["compliance"]
        mix = self.state.get("mix")
        return [f"c{k + 1}" for k in range(np.shape(mix)[1])] if mix else ["c1"]

    def coefficient_unit(self) -> str:
        if self.from_masses:
            return "rad/(N m)"  # joint deflection per N m of gravity torque: 1 / stiffness
        return "rad/m"  # joint deflection per metre of lever arm of the weight downstream

    def _levers(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        """Lever arms (N, K) in metres about joint `joint`'s axis of gravity on each downstream point."""
        j, n = self.joint_index, nominal.n_joints
        key = ("gravity_axes_points", id(nominal))  # one chain shared by every gravity effect of the model
        packed = ctx.cache.get(key)
        if packed is None:  # (N, 3, M), row for row like every cache entry: n axes, n + 1 origins, tool
            T_flange, Z, O = chain_axes(nominal, ctx.q)
            parts = [Z, O]
            if ctx.p_flange_tool is not None:
                tip = np.einsum("nij,nj->ni", T_flange[:, :3, :3], ctx.p_flange_tool) + T_flange[:, :3, 3]
                parts.append(tip.T[None])
            packed = ctx.cache[key] = np.concatenate(parts).transpose(2, 1, 0)
        cols = packed.transpose(2, 1, 0)  # (M, 3, N)
        z, o = cols[j], cols[n + j]
        points = cols[n + j + 1 :]  # (K, 3, N): the downstream link origins, then the tool point
        # z . ((p - o) x g) = (g x z) . (p - o): one cross product per joint, not per point.
        g = GRAVITY_DIRECTION_BASE
        u = np.stack([g[1] * z[2] - g[2] * z[1], g[2] * z[0] - g[0] * z[2], g[0] * z[1] - g[1] * z[0]])
        L = ((points - o) * u).sum(axis=1).T
        if ctx.payload_kg is not None and L.shape[1] > 0:
            L = np.column_stack([L, L[:, -1] * ctx.payload_kg])
        return L

    def torque(
        self, ctx: EffectContext, nominal: KinematicModel, levers: np.ndarray | None = None
    ) -> np.ndarray:
        """Gravity torque (N,) in N m about joint `joint`'s axis from the link masses in the state: link k (the
        one joint k moves) weighs at the middle of frame origins k-1 and k, a recorded payload at the tool.
        `levers`: `_levers` on these rows when the caller has them."""
        masses = np.asarray(self.state["masses_kg"], dtype=float)
        j, n = self.joint_index, len(masses)
        L = self._levers(ctx, nominal) if levers is None else levers  # origins j+1 .. n, the tool, (payload)
        arms = np.column_stack([np.zeros(len(L)), L[:, : n - j]])  # origin j lies on the axis itself
        per_g = 0.5 * (arms[:, :-1] + arms[:, 1:]) @ masses[j:]
        if ctx.payload_kg is not None and ctx.p_flange_tool is not None:
            per_g = per_g + ctx.payload_kg * L[:, n - j]
        return STANDARD_GRAVITY_M_S2 * per_g

    def prepare(self, ctx: EffectContext, nominal: KinematicModel) -> bool:
        L = self._levers(ctx, nominal)
        if np.max(np.abs(L)) < 1e-6:  # a vertical axis carries no gravity torque
            return False
        if nominal.link_masses_kg is not None:  # masses known: one compliance per joint
            masses = [float(m) for m in nominal.link_masses_kg]
            self.state = {
                "masses_kg": masses,
                "torque_max_nm": stretched_torque_nm(nominal, self.joint_index),
            }
            self.params = np.zeros(1)
            return bool(np.max(np.abs(self.torque(ctx, nominal, L))) > MIN_GRAVITY_TORQUE_NM)
        # Merge lever arms the data cannot tell apart: keep SVD directions above 1e-3 of the largest.
        _, s, Vt = np.linalg.svd(L, full_matrices=False)
        keep = s > 1e-3 * s[0]
        self.state = {"mix": Vt[keep].T.tolist()}  # (K, r)
        self.params = np.zeros(int(keep.sum()))
        return True

    def regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        if self.from_masses:
            return self.torque(ctx, nominal)[:, None]
        mix = np.asarray(self.state["mix"], dtype=float)
        L = self._levers(ctx, nominal)
        if L.shape[1] != mix.shape[0]:  # payload column present in one dataset only
            L = L[:, : mix.shape[0]] if L.shape[1] > mix.shape[0] else np.pad(L, ((0, 0), (0, 1)))
        return L @ mix

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        deflection = np.rad2deg(self.regressors(ctx, nominal) @ self.params) * 1e3
        out = {
            "deflection_rms_mdeg": float(np.sqrt(np.mean(deflection**2))),
            "deflection_min_mdeg": float(deflection.min()),
            "deflection_max_mdeg": float(deflection.max()),
        }
        if self.from_masses and self.params[0] > 0:
            out["stiffness_knm_per_rad"] = float(1e-3 / self.params[0])
        return out

    def implausible(self, ctx: EffectContext, nominal: KinematicModel) -> str | None:
        """Beyond the plausible swing, or (torque form) a joint that would yield against gravity."""
        if self.from_masses and self.params[0] < 0:
            return (
                f"implausible sign: joint {self.joint} would yield against the gravity torque (a negative "
                "compliance); it is fitting something else"
            )
        return super().implausible(ctx, nominal)

    def prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        if not physical(self) or self.state.get("prior_dropped"):
            return None
        return np.zeros(1), np.array([self.state["prior_std"]])

    def driver(self, ctx: EffectContext, nominal: KinematicModel) -> tuple[str, np.ndarray]:
        """The fitted deflection, i.e. the gravity torque over the stiffness, in millidegrees."""
        deflection = self.regressors(ctx, nominal) @ self.params
        return f"joint {self.joint} gravity deflection = torque / stiffness (mdeg)", np.rad2deg(
            deflection
        ) * 1e3


# A harmonic of a joint's angle is offered only where the sampled range covers this many of its periods:
# over a shorter arc sin/cos look like a polynomial the geometry (offset, scale) imitates, and the fit
# extrapolates wildly. The 1st harmonic then needs ~0.8 of a turn, the 2nd ~0.4.
CYCLIC_MIN_PERIODS = 0.8


class Cyclic(Effect):
    family = "cyclic"

    def harmonics(self) -> list[int]:
        return list(self.state.get("harmonics", [1, 2]))

    def coefficient_names(self) -> list[str]:
        return [f"{f}{h}" for h in self.harmonics() for f in ("sin", "cos")]

    def coefficient_unit(self) -> str:
        return "rad"

    def prepare(self, ctx: EffectContext, nominal: KinematicModel) -> bool:
        span = float(np.ptp(ctx.q[:, self.joint_index]))
        harmonics = [h for h in (1, 2) if span >= CYCLIC_MIN_PERIODS * 2 * np.pi / h]
        self.state = {"harmonics": harmonics, "range_rad": span}
        self.params = np.zeros(2 * len(harmonics))
        return bool(harmonics)

    def regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        qj = ctx.q[:, self.joint_index]
        return np.stack([f(h * qj) for h in self.harmonics() for f in (np.sin, np.cos)], axis=1)

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        out = {}
        for k, h in enumerate(self.harmonics()):  # a sin x + b cos x = hypot(a, b) sin(x + atan2(b, a))
            s, c = self.params[2 * k : 2 * k + 2]
            out[f"amplitude{h}_mdeg"] = float(np.rad2deg(np.hypot(s, c)) * 1e3)
            out[f"phase{h}_deg"] = float(np.rad2deg(np.arctan2(c, s)))
        return out

    def driver(self, ctx: EffectContext, nominal: KinematicModel) -> tuple[str, np.ndarray]:
        return f"joint {self.joint} angle (deg)", np.rad2deg(ctx.q[:, self.joint_index])


def approach_signs(q: np.ndarray, tol_rad: float = 2e-5) -> np.ndarray:
    """Sign (+1/-1) of the last motion of each joint before each row, from the row order.

    A joint that did not move keeps its previous sign; before its first motion the sign is 0 (unknown).
    """
    step = np.diff(q, axis=0, prepend=q[:1])
    rows = np.arange(q.shape[0])[:, None]
    last_move = np.maximum.accumulate(np.where(np.abs(step) > tol_rad, rows, -1), axis=0)  # forward fill
    signs = np.sign(np.take_along_axis(step, np.maximum(last_move, 0), axis=0))
    return np.where(last_move >= 0, signs, 0.0)


class Backlash(Effect):
    family = "backlash"

    def coefficient_names(self) -> list[str]:
        return ["half_gap"]

    def coefficient_unit(self) -> str:
        return "rad"

    def prepare(self, ctx: EffectContext, nominal: KinematicModel) -> bool:
        s = self.regressors(ctx, nominal)[:, 0]
        self.params = np.zeros(1)
        return bool(min(np.sum(s > 0), np.sum(s < 0)) >= 5)  # needs both sides, several times

    def regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        signs = approach_signs(ctx.q) if ctx.approach is None else ctx.approach
        return signs[:, self.joint_index : self.joint_index + 1]

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        return {"half_gap_mdeg": float(np.rad2deg(self.params[0]) * 1e3)}

    def driver(self, ctx: EffectContext, nominal: KinematicModel) -> tuple[str, np.ndarray]:
        return f"joint {self.joint} approach direction (sign)", self.regressors(ctx, nominal)[:, 0]


class JointScale(Effect):
    family = "joint_scale"

    def coefficient_names(self) -> list[str]:
        return ["scale"]

    def coefficient_unit(self) -> str:
        return "rad/rad"

    def regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        return ctx.q[:, self.joint_index : self.joint_index + 1]

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        return {"scale_ppm": float(self.params[0] * 1e6)}

    def driver(self, ctx: EffectContext, nominal: KinematicModel) -> tuple[str, np.ndarray]:
        return f"joint {self.joint} angle (deg)", np.rad2deg(ctx.q[:, self.joint_index])


def _thermal_driver(ctx: EffectContext) -> tuple[str, np.ndarray] | None:
    """Temperature when it varies, else time; None when the data has neither."""
    if ctx.temperature_c is not None and np.nanstd(ctx.temperature_c) > 0.02:
        return "temperature_c", ctx.temperature_c
    if ctx.t_s is not None and np.ptp(ctx.t_s) > 0:
        return "t_s", ctx.t_s
    return None


class _Thermal(Effect):
    def prepare(self, ctx: EffectContext, nominal: KinematicModel) -> bool:
        found = _thermal_driver(ctx)
        self.params = np.zeros(len(self.coefficient_names()))
        if found is None:
            return False
        name, values = found
        self.state = {"driver": name, "reference": float(np.mean(values))}
        return True

    def delta(self, ctx: EffectContext) -> np.ndarray:
        """The driver less its training reference per row. The material's growth (`material_growth`) without a
        temperature is taken at its reference (no growth): a model that merely carries the physics predicts
        as a geometric one where no temperature is known (the callers that know one pass it and warn)."""
        name = self.state["driver"]
        values = ctx.temperature_c if name == "temperature_c" else ctx.t_s
        if values is None and material_growth(self):
            return np.zeros(ctx.n)
        if values is None:
            raise ValueError(f"the model's {self.family} effect needs the '{name}' column in the data")
        return np.asarray(values, float) - self.state["reference"]

    def regressors(self, ctx: EffectContext, nominal: KinematicModel) -> np.ndarray:
        return self.delta(ctx)[:, None]

    def driver_unit(self) -> str:
        """K for a temperature-driven effect, s for a time-driven one."""
        return "K" if self.state.get("driver", "temperature_c") == "temperature_c" else "s"

    def coefficient_unit(self) -> str:
        return f"{'m' if self.kind == 'offset' else '1'}/{self.driver_unit()}"

    def driver(self, ctx: EffectContext, nominal: KinematicModel) -> tuple[str, np.ndarray]:
        unit = "°C" if self.state["driver"] == "temperature_c" else "s"
        return f"{self.state['driver']} - reference ({unit})", self.delta(ctx)


class ThermalExpansion(_Thermal):
    family = "thermal_expansion"
    kind = "growth"

    def implausible(self, ctx: EffectContext, nominal: KinematicModel) -> str | None:
        k = abs(float(self.params[0]))
        if self.state["driver"] == "temperature_c" and k > PLAUSIBLE_EXPANSION_PER_K:
            return f"implausible size: {k * 1e6:.3g} ppm/K (metals expand 10-25 ppm/K)"
        growth = k * float(np.ptp(self.delta(ctx)))
        if growth > PLAUSIBLE_EXPANSION_PER_K * 20:  # 20 K of warm-up at most
            return f"implausible size: the links would grow {growth * 1e6:.3g} ppm over the campaign"
        return None

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        unit = "K" if self.state["driver"] == "temperature_c" else "s"
        out = {f"expansion_ppm_per_{unit}": float(self.params[0] * 1e6)}
        if material_growth(self):
            out["material_ppm_per_K"] = float(self.state["material_per_k"] * 1e6)
        return out

    def coefficient_names(self) -> list[str]:
        return ["per_unit"]

    def prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        if not material_growth(self) or self.state.get("prior_dropped"):
            return None
        return np.array([self.state["material_per_k"]]), np.array([self.state["prior_std_per_k"]])


class ThermalDrift(_Thermal):
    family = "thermal_drift"
    kind = "offset"

    def implausible(self, ctx: EffectContext, nominal: KinematicModel) -> str | None:
        drift = float(np.ptp(self.delta(ctx)) * np.linalg.norm(self.params))
        if drift <= PLAUSIBLE_DRIFT_M:
            return None
        return f"implausible size: the base would drift {drift * 1000:.3g} mm over the campaign"

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        unit = "K" if self.state["driver"] == "temperature_c" else "s"
        return {f"drift_um_per_{unit}": float(np.linalg.norm(self.params) * 1e6)}

    def coefficient_names(self) -> list[str]:
        return ["vx", "vy", "vz"]


class TrackerScale(_Thermal):
    family = "tracker_scale"
    kind = "scale"

    def implausible(self, ctx: EffectContext, nominal: KinematicModel) -> str | None:
        s = abs(float(self.params[0]))
        if self.state["driver"] == "temperature_c" and s > PLAUSIBLE_TRACKER_SCALE_PER_K:
            return f"implausible size: {s * 1e6:.3g} ppm/K (a wrong air temperature gives about 1 ppm/K)"
        scale = s * float(np.ptp(self.delta(ctx)))
        if scale > PLAUSIBLE_TRACKER_SCALE:
            return (
                f"implausible size: the tracker's scale would change {scale * 1e6:.3g} ppm over the campaign"
            )
        return None

    def summary(self, ctx: EffectContext, nominal: KinematicModel) -> dict[str, float]:
        unit = "K" if self.state["driver"] == "temperature_c" else "s"
        out = {f"scale_ppm_per_{unit}": float(self.params[0] * 1e6)}
        if unit == "K":  # the air temperature error that explains it, per K of the recorded temperature
            out["air_error_k_per_K"] = float(self.params[0] / REFRACTION_PER_K)
        return out

    def coefficient_names(self) -> list[str]:
        return ["per_unit"]

    def prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        if not stuck_air_scale(self) or self.state.get("prior_dropped"):
            return None
        return np.array([self.state["prior_mean_per_k"]]), np.array([self.state["prior_std_per_k"]])


_CLASSES: dict[str, type[Effect]] = {
    c.family: c
    for c in (GravityCompliance, Cyclic, Backlash, JointScale, ThermalExpansion, ThermalDrift, TrackerScale)
}
JOINT_FAMILIES = ("gravity_compliance", "cyclic", "backlash", "joint_scale")
# driven by a measured temperature (or time)
THERMAL_FAMILIES = ("thermal_expansion", "thermal_drift", "tracker_scale")


def temperature_driven(eff: Effect) -> bool:
    """A thermal effect driven by a recorded temperature (not by time: time also orders the poses)."""
    return eff.family in THERMAL_FAMILIES and eff.state.get("driver") == "temperature_c"


# A physics term's data contradict its prior when the value the data alone give lies more than this many
# standard deviations (of the difference: data's and prior's combined) from the prior's mean: the model then
# follows the data (`without_prior`) and the report says so with both values. About 1 in 100 campaigns that
# agree with their prior cross it by chance, and crossing it only drops the prior the data outweigh anyway.
PRIOR_CONFLICT_SIGMAS = 2.5

# 1-sigma of the material prior, as a fraction of the material's coefficient: an arm is not one alloy (steel
# gears and bearings in aluminium tubes), and the temperature read (a probe on one link, or the air) is not
# the mean temperature of every link. A campaign spanning a few kelvin over a metre of reach measures the
# coefficient better than this and follows its data; one spanning a fraction of a kelvin keeps the material's.
EXPANSION_PRIOR_FRACTION = 0.3


def physical(eff: Effect) -> bool:
    """A term the physics puts in the model (the links' material growth, the joints' yield under the link
    masses' gravity, the tracker's scale from an air reading that stays put): never selected or removed."""
    return material_growth(eff) or "prior_std" in eff.state or stuck_air_scale(eff)


def material_growth(eff: Effect) -> bool:
    """The links' material growth (`material_expansion`)."""
    return "material_per_k" in eff.state


def material_expansion(ctx: EffectContext, nominal: KinematicModel) -> ThermalExpansion | None:
    """The links' thermal growth driven by the recorded temperature, its coefficient starting at the
    material's (`nominal.expansion_per_k`) with that as its prior (`EXPANSION_PRIOR_FRACTION`); None when
    the robot names no material or the data lack a temperature on some row."""
    k0 = nominal.expansion_per_k
    temps = ctx.temperature_c
    if k0 is None or temps is None or len(temps) == 0 or not np.all(np.isfinite(temps)):
        return None
    eff = ThermalExpansion()
    eff.state = {
        "driver": "temperature_c",
        "reference": float(np.mean(temps)),
        "material_per_k": float(k0),
        "prior_std_per_k": float(EXPANSION_PRIOR_FRACTION * k0),
    }
    eff.params = np.array([float(k0)])
    return eff


# The tracker's scale when its air reading stays put while the recorded temperature rises
# (`stuck_air_tracker_scale`): the distances scale by REFRACTION_PER_K per K the real air warmed, and how much
# the air warmed per K of the recorded temperature (f) is not in the data. In a hall it lies between 0 (the air
# stays put, only the arm warms: the reading may even be right) and 1 (the air warms as the arm does; a
# little more where the structure's probe lags the air). A Gaussian of mean 0.5 and 1-sigma 0.5 in f spans that
# range at one sigma either side and leaves room beyond it (sun on the tracker, a door opened), where a uniform
# over [0, 1] would have half the width and forbid what the data might show. Taken from the physics of
# refraction and of halls, not from any simulated cell.
STUCK_AIR_PRIOR_FRACTION = 0.5
STUCK_AIR_PRIOR_STD_FRACTION = 0.5


def stuck_air_scale(eff: Effect) -> bool:
    """The tracker's scale put in the model because its air reading stayed put (`stuck_air_tracker_scale`)."""
    return eff.family == "tracker_scale" and "air_read_c" in eff.state


def stuck_air_tracker_scale(ctx: EffectContext, air_read_c: float) -> TrackerScale | None:
    """The tracker's scale driven by the recorded temperature, its coefficient starting at the prior's mean
    (STUCK_AIR_PRIOR_FRACTION of REFRACTION_PER_K, 1-sigma STUCK_AIR_PRIOR_STD_FRACTION of it), for a
    campaign whose air reading stayed at `air_read_c` (the caller decides that it did); None when some row
    lacks a temperature."""
    temps = ctx.temperature_c
    if temps is None or len(temps) == 0 or not np.all(np.isfinite(temps)):
        return None
    eff = TrackerScale()
    mean = STUCK_AIR_PRIOR_FRACTION * REFRACTION_PER_K
    eff.state = {
        "driver": "temperature_c",
        "reference": float(np.mean(temps)),
        "air_read_c": float(air_read_c),
        "prior_mean_per_k": float(mean),
        "prior_std_per_k": float(STUCK_AIR_PRIOR_STD_FRACTION * abs(REFRACTION_PER_K)),
    }
    eff.params = np.array([float(mean)])
    return eff


def without_prior(eff: Effect, prior_value: float) -> Effect:
    """A physics term whose data contradict its prior: fitted from the data alone (no prior), remembering the
    value the prior-weighted fit had made of it."""
    free = type(eff)(joint=eff.joint, params=eff.params.copy(), state=dict(eff.state))
    free.state.update(prior_dropped=True, with_prior=float(prior_value))
    return free


def hold_absent(eff: Effect, data_value: float) -> Effect:
    """A physics term the data reject (they carry most of what is known of it and find it no different from
    zero): held at zero (no growth, a rigid joint: the geometric model's own assumption), remembering what
    the data had made of it."""
    held = type(eff)(joint=eff.joint, params=np.zeros(len(eff.params)), state=dict(eff.state))
    held.state.update(held=True, rejected=True, data_value=float(data_value))
    return held


def gravity_physics_term(eff: Effect) -> bool:
    """A joint's yield under the link masses' gravity put in the model as physics (`gravity_physics`)."""
    return isinstance(eff, GravityCompliance) and physical(eff)


def yields_against_gravity(eff: Effect) -> bool:
    """A free gravity physics term whose fitted compliance is negative: the joint would yield against gravity,
    so the term stands in for something else (`hold_rigid` holds it at a rigid joint)."""
    return gravity_physics_term(eff) and not eff.held and float(eff.params[0]) < 0


def hold_rigid(eff: Effect, negative_compliance: float) -> Effect:
    """A gravity physics term held at zero compliance (a rigid joint), remembering the negative compliance
    the data had made of it: no joint yields against gravity."""
    held = type(eff)(joint=eff.joint, params=np.zeros(1), state=dict(eff.state))
    held.state.update(held=True, negative_compliance=float(negative_compliance))
    return held


# Gravity below this torque (N m) on every row is no torque: an axis along gravity, or only on-axis masses.
MIN_GRAVITY_TORQUE_NM = 1e-3

# The prior of a joint's gravity compliance (the physics term, `gravity_physics`): centred on 0 (a rigid
# joint: the geometric model's own assumption, so a campaign that cannot see the yield predicts as the
# geometric fit does), with a 1-sigma of this deflection at the joint's largest gravity torque (the arm
# stretched horizontally, `stretched_torque_nm`). Arms deflect about 0.5-2 mrad there (the public UR10
# campaigns: 1.5-2 mrad on joint 2; harmonic drives: 1-3 arcmin at rated torque), so the data outweigh the
# prior wherever they see the yield at all, and a joint they cannot see keeps a deflection of about zero.
GRAVITY_PRIOR_DEFLECTION_RAD = 2e-3


def stretched_torque_nm(nominal: KinematicModel, joint_index: int) -> float:
    """A bound of the gravity torque about a joint from the link masses: every link downstream held out
    horizontally in one line, each mass at the middle of its span (the span between two frame origins)."""
    masses = np.asarray(nominal.link_masses_kg, dtype=float)
    spans = np.hypot(np.asarray(nominal.a, float), np.asarray(nominal.d, float))[joint_index:]
    reach = np.cumsum(spans) - 0.5 * spans  # from joint's axis to each downstream link's middle
    return float(STANDARD_GRAVITY_M_S2 * np.sum(masses[joint_index:] * reach))


# The joints that carry the arm's weight: those whose largest gravity torque (`stretched_torque_nm`) is at least
# this share of the most loaded joint's (among the joints gravity loads: a vertical base axis carries none). A
# wrist is sized for the payload, not for the arm's own links: on a UR10 joints 4-6 carry at most 5 % of joint
# 2's torque and yield micro-radians, which a campaign cannot tell from the wrist's geometry, while their torque
# is mostly one harmonic of the joint's angle and would stand in for other effects (on the public series B joint
# 5's compliance came out negative, a joint yielding against gravity). Their yield stays a candidate (one
# compliance, the torque from the masses), tested like any other. A heavy industrial wrist passes (an IRB 2600
# with its masses: joint 4 at 16 % of joint 2's).
GRAVITY_PHYSICS_TORQUE_SHARE = 0.1


def gravity_physics(ctx: EffectContext, nominal: KinematicModel) -> list[GravityCompliance]:
    """The joints' yield under gravity as physics when the robot names its link masses: one compliance per
    joint that carries the arm's weight (GRAVITY_PHYSICS_TORQUE_SHARE) and a torque on these rows, starting at
    0 with its prior (GRAVITY_PRIOR_DEFLECTION_RAD); none when the masses are unknown (the free form is then a
    candidate)."""
    if nominal.link_masses_kg is None:
        return []
    # Only joints gravity loads on these rows compete for "most loaded": a vertical axis (a base joint)
    # carries none, however far its links reach.
    loaded = [
        eff
        for eff in (GravityCompliance(joint=j) for j in range(1, nominal.n_joints + 1))
        if eff.prepare(ctx, nominal)
    ]
    if not loaded:
        return []
    most = max(eff.state["torque_max_nm"] for eff in loaded)
    out = [eff for eff in loaded if eff.state["torque_max_nm"] >= GRAVITY_PHYSICS_TORQUE_SHARE * most]
    for eff in out:
        eff.state["prior_std"] = GRAVITY_PRIOR_DEFLECTION_RAD / eff.state["torque_max_nm"]
    return out


def make_effect(family: str, joint: int | None = None) -> Effect:
    """A fresh (unfitted) effect of a documented family."""
    if family not in _CLASSES:
        raise ValueError(f"unknown effect family '{family}'; known: {', '.join(EFFECT_FAMILIES)}")
    if (family in JOINT_FAMILIES) != (joint is not None):
        raise ValueError(f"effect '{family}' {'needs' if family in JOINT_FAMILIES else 'takes no'} joint")
    return _CLASSES[family](joint=joint)


def effect_from_dict(data: dict) -> Effect:
    """Rebuild an effect saved by `Effect.to_dict`."""
    eff = make_effect(data["family"], data.get("joint"))
    eff.state = dict(data.get("state", {}))
    eff.params = np.asarray(data["params"], dtype=float)
    return eff


def candidate_effects(
    ctx: EffectContext,
    nominal: KinematicModel,
    present: list[Effect],
    families: tuple[str, ...] | None = None,
) -> list[Effect]:
    """Every effect not yet in the model that this dataset could reveal, prepared on its rows."""
    have = {(e.family, e.joint) for e in present}
    out: list[Effect] = []
    for family in families or EFFECT_FAMILIES:
        joints = range(1, nominal.n_joints + 1) if family in JOINT_FAMILIES else [None]
        for j in joints:
            if (family, j) in have:
                continue
            eff = make_effect(family, j)
            if eff.prepare(ctx, nominal):
                out.append(eff)
    return out


def growth_direction(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """d p_base / d k for all link lengths scaled by (1 + k), the tool and the fixed flange transform unchanged:
    (N, 3), metres. Every translation along the chain is a link length, so the last link's origin scales with
    them and the tool point moves with it: the derivative is that origin (exact, where a finite difference of
    two forward kinematics carried 1e-10 of rounding and cost ten times as much)."""
    return last_link_origins(model, q)


def tool_points_and_growth_direction(
    model: KinematicModel, q: np.ndarray, p_flange_tool_rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`tool_points` (one tool point per row) and `growth_direction` (N, 3) each, from one pass over the chain."""
    T, growth = flange_poses_and_last_origins(model, q)
    return points_on_flanges(T, p_flange_tool_rows), growth
