"""A calibrated robot model: geometry, base frame, tool points, effects; predicts, corrects, saves as JSON.

The full parameter vector is the kinematic parameters (`KinematicModel.param_names`), the six base
parameters (tracker <- robot base, see `hil.geometry.kinematics.perturb_base`), three tool coordinates per SMR
nest, three orientation parameters per 6-DoF probe (a small rotation of R_flange_probe about the flange
axes: R <- Rot(d) R), then every effect's coefficients. `predict` applies all of it; `jacobian_ctx`
differentiates it; `rotation_jacobian_ctx` does the same for the probe's orientation.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from hil.data.dataset import joints_rad, make_dataset, orientations, points_m, smr_ids
from hil.data.jsonable import to_jsonable
from hil.geometry.ik import solve_ik
from hil.geometry.kinematics import (
    BASE_PARAM_NAMES,
    KinematicModel,
    forward_kinematics,
    identification_jacobian,
    kinematic_rotation_jacobian,
    perturb_base,
    tool_points,
)
from hil.geometry.robots import get_robot
from hil.geometry.se3 import fit_rigid, invert, make_transform, transform_points
from hil.model.effects import (
    Effect,
    EffectContext,
    effect_from_dict,
    tool_points_and_growth_direction,
)
from hil.model.intervals import PredictionSpread
from hil.model.residual_maps import map_from_dict

# Format 2 adds the prediction spread (hil.model.intervals); a format-1 file still loads and predicts, but
# gives no interval.
FORMAT = "hil-calibrated-model/2"
READABLE_FORMATS = ("hil-calibrated-model/1", FORMAT)


@dataclass
class CalibratedModel:
    """Everything needed to predict where the SMR is in the tracker frame for given joints."""

    robot: str
    nominal: KinematicModel
    kinematic: KinematicModel
    T_tracker_base: np.ndarray
    tools: dict[int, np.ndarray]  # SMR nest id -> tool point in the flange (m)
    effects: list[Effect] = field(default_factory=list)
    info: dict = field(default_factory=dict)  # solver report: std errors, dropped parameters, outliers...
    residual_map: dict | None = None  # fallback residual map (hil.model.residual_maps), applied by `predict`
    probes: dict[int, np.ndarray] = field(default_factory=dict)  # SMR nest id -> R_flange_probe (3, 3)
    spread: PredictionSpread | None = None  # what prediction intervals need (hil.model.intervals)
    file_format: str = FORMAT  # the format the model was read from (a format-1 file has no spread)

    @property
    def format_version(self) -> int:
        return int(self.file_format.rsplit("/", 1)[1])

    # ----- parameter vector ---------------------------------------------------------------------
    @property
    def param_names(self) -> list[str]:
        names = list(self.kinematic.param_names) + list(BASE_PARAM_NAMES)
        for smr in sorted(self.tools):
            names += [f"tool{smr}_x", f"tool{smr}_y", f"tool{smr}_z"]
        for smr in sorted(self.probes):
            names += [f"probe{smr}_rx", f"probe{smr}_ry", f"probe{smr}_rz"]
        for eff in self.effects:
            names += eff.param_names
        return names

    def effect_slices(self) -> list[slice]:
        """Where each effect's coefficients sit in the parameter vector."""
        start = len(self.kinematic.param_names) + 6 + 3 * len(self.tools) + 3 * len(self.probes)
        out = []
        for eff in self.effects:
            out.append(slice(start, start + len(eff.params)))
            start += len(eff.params)
        return out

    def apply_increment(self, dx: np.ndarray) -> CalibratedModel:
        """A new model with the increment dx (full parameter order) applied."""
        dx = np.asarray(dx, dtype=float)
        nk = len(self.kinematic.param_names)
        kin = self.kinematic.with_params(self.kinematic.params + dx[:nk])
        T = perturb_base(self.T_tracker_base, dx[nk : nk + 6])
        tools = {}
        pos = nk + 6
        for smr in sorted(self.tools):
            tools[smr] = self.tools[smr] + dx[pos : pos + 3]
            pos += 3
        probes = {}
        for smr in sorted(self.probes):
            probes[smr] = Rotation.from_rotvec(dx[pos : pos + 3]).as_matrix() @ self.probes[smr]
            pos += 3
        effects = []
        for eff, sl in zip(self.effects, self.effect_slices(), strict=True):
            new = type(eff)(joint=eff.joint, params=eff.params + dx[sl], state=eff.state)
            effects.append(new)
        return replace(self, kinematic=kin, T_tracker_base=T, tools=tools, effects=effects, probes=probes)

    def with_effect(self, effect: Effect) -> CalibratedModel:
        return replace(self, effects=[*self.effects, effect])

    # ----- prediction ---------------------------------------------------------------------------
    def context(self, df: pd.DataFrame) -> tuple[EffectContext, np.ndarray]:
        """Effect context and per-row tool points (N, 3) for a dataset frame."""
        q = joints_rad(df, self.kinematic.n_joints)
        ctx = EffectContext.from_frame(df, q)
        p_flange_tool = self._row_tools(smr_ids(df))
        ctx.p_flange_tool = p_flange_tool
        return ctx, p_flange_tool

    def _row_tools(self, smr: np.ndarray) -> np.ndarray:
        ids, inverse = np.unique(smr, return_inverse=True)  # one lookup per nest, not per row
        missing = sorted(set(ids.tolist()) - set(self.tools))
        if missing:
            raise ValueError(
                f"the model knows tool points for SMR nests {sorted(self.tools)}, the data uses {missing}; "
                "calibrate with data that contains those nests"
            )
        return np.array([self.tools[int(s)] for s in ids]).reshape(-1, 3)[inverse.ravel()]

    def joint_offsets(self, ctx: EffectContext) -> np.ndarray:
        """Output-side joint offsets (N, n) from every joint effect."""
        dq = np.zeros_like(ctx.q)
        for eff in self.effects:
            if eff.kind == "joint":
                dq[:, eff.joint_index] += eff.cached_regressors(ctx, self.nominal) @ eff.params
        return dq

    def predict_ctx(self, ctx: EffectContext) -> np.ndarray:
        """Predicted SMR centres (N, 3) in the tracker frame, metres."""
        return self._predict_and_growth_direction(ctx)[0]

    def _predict_and_growth_direction(self, ctx: EffectContext) -> tuple[np.ndarray, np.ndarray]:
        """`predict_ctx` and the links' growth direction (N, 3, base frame) at the effective joints, from one
        pass over the chain (the Jacobian needs both)."""
        q_eff = ctx.q + self.joint_offsets(ctx)
        p_base, growth = tool_points_and_growth_direction(self.kinematic, q_eff, _context_tools(ctx))
        offset = np.zeros_like(p_base)
        scale = np.zeros(len(p_base))
        for eff in self.effects:
            if eff.kind == "growth":
                g = eff.cached_regressors(ctx, self.nominal) @ eff.params
                p_base = p_base + g[:, None] * growth
            elif eff.kind == "offset":
                offset += eff.cached_regressors(ctx, self.nominal)[:, :1] * eff.params[None, :]
            elif eff.kind == "scale":
                scale += eff.cached_regressors(ctx, self.nominal) @ eff.params
        R, t = self.T_tracker_base[:3, :3], self.T_tracker_base[:3, 3]
        return (p_base @ R.T + t + offset) * (1.0 + scale)[:, None], growth  # the tracker scales what it sees

    def predict(self, df: pd.DataFrame, with_map: bool = True) -> np.ndarray:
        """Predicted SMR centres (N, 3) in the tracker frame (m) for the joints (and drivers) in df.

        Applies geometry, base, tool, every effect and, when the model carries one, the residual map
        (which warns for targets outside the measured volume).
        """
        ctx, _ = self.context(df)
        p = self.predict_ctx(ctx)
        if with_map and self.residual_map is not None:
            q_eff = ctx.q + self.joint_offsets(ctx)
            p_base = tool_points(self.kinematic, q_eff, _context_tools(ctx))
            p = p + map_from_dict(self.residual_map).predict(ctx.q, p_base)
        return p

    def predict_poses(self, q: np.ndarray, smr: int | None = None) -> np.ndarray:
        """Poses T_tracker_tool (N, 4, 4) the model predicts for commanded joints q (N, n): the SMR centre of
        `predict` (every effect and the residual map) with the flange's orientation through the joint
        effects. Built on the public dataset path, it judges compensated joints independently of
        `hil.compensation.model_based`'s own predictor."""
        q = self.kinematic.check_joints(q)
        sid = sorted(self.tools)[0] if smr is None else int(smr)
        df = make_dataset(q, np.zeros((len(q), 3)), smr=sid)
        p = self.predict(df)
        ctx, _ = self.context(df)
        R_base_flange = forward_kinematics(self.kinematic, q + self.joint_offsets(ctx))[:, :3, :3]
        return make_transform(self.T_tracker_base[:3, :3] @ R_base_flange, p)

    def jacobian_ctx(self, ctx: EffectContext, smr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted points (N, 3) and d(points)/d(parameters) (N, 3, P) in the full parameter order; an effect
        whose coefficients are held (`Effect.held`) has zero columns, so no fit or identifiability test frees
        them."""
        q_eff = ctx.q + self.joint_offsets(ctx)
        N = ctx.n
        nk = len(self.kinematic.param_names)
        P = len(self.param_names)
        J = np.zeros((N, 3, P))
        ids = sorted(self.tools)
        for k, sid in enumerate(ids):
            rows = np.flatnonzero(smr == sid)
            if rows.size == 0:
                continue
            _, Jg = identification_jacobian(self.kinematic, q_eff[rows], self.T_tracker_base, self.tools[sid])
            J[rows, :, : nk + 6] = Jg[:, :, : nk + 6]
            J[np.ix_(rows, np.arange(3), np.arange(nk + 6 + 3 * k, nk + 9 + 3 * k))] = Jg[:, :, nk + 6 :]
        # A joint offset moves the point like the joint itself: the theta column of that joint.
        theta_cols = [
            self.kinematic.param_names.index(f"theta{j + 1}") for j in range(self.kinematic.n_joints)
        ]
        R = self.T_tracker_base[:3, :3]
        p, growth = self._predict_and_growth_direction(ctx)
        scale = sum(
            (e.cached_regressors(ctx, self.nominal) @ e.params for e in self.effects if e.kind == "scale"),
            np.zeros(N),
        )
        for eff, sl in zip(self.effects, self.effect_slices(), strict=True):
            reg = eff.cached_regressors(ctx, self.nominal)
            if eff.kind == "joint":
                col = J[:, :, theta_cols[eff.joint_index]]
                J[:, :, sl] = col[:, :, None] * reg[:, None, :]
            elif eff.kind == "growth":
                G = growth @ R.T
                J[:, :, sl] = G[:, :, None] * reg[:, None, :]
            elif eff.kind == "scale":  # the point before the tracker's scale
                J[:, :, sl] = (p / (1.0 + scale)[:, None])[:, :, None] * reg[:, None, :]
            else:
                J[:, :, sl] = reg[:, :1, None] * np.eye(3)[None]
        for eff, sl in zip(self.effects, self.effect_slices(), strict=True):
            if eff.held:
                J[:, :, sl] = 0.0
        if np.any(scale):  # the tracker's scale stretches every other parameter's motion too
            others = np.ones(P, bool)
            for eff, sl in zip(self.effects, self.effect_slices(), strict=True):
                others[sl] = eff.kind != "scale"
            J[:, :, others] *= (1.0 + scale)[:, None, None]
        return p, J

    def _row_probes(self, smr: np.ndarray) -> np.ndarray:
        """R_flange_probe of every row (N, 3, 3); a nest without one is named."""
        ids, inverse = np.unique(smr, return_inverse=True)
        missing = sorted(set(ids.tolist()) - set(self.probes))
        if missing:
            raise ValueError(
                f"the model knows probe orientations for SMR nests {sorted(self.probes)}, the data uses "
                f"{missing}; calibrate with orientation data (rx_deg, ry_deg, rz_deg) of those nests"
            )
        return np.array([self.probes[int(s)] for s in ids]).reshape(-1, 3, 3)[inverse.ravel()]

    def rotation_jacobian_ctx(self, ctx: EffectContext, smr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted probe orientations R_tracker_probe (N, 3, 3) and their angular derivative (N, 3, P)
        in the tracker frame, full parameter order: a change dx turns the prediction by Rot(J dx) on the
        left. Kinematic columns are the turning axes (`kinematic_rotation_jacobian`), base rotation turns
        it about the base axes, a probe's own parameters about the flange axes; lengths, tool points,
        thermal growth, drift and the tracker's scale do not turn it; a joint effect turns it like its joint."""
        R_FP = self._row_probes(smr)
        q_eff = ctx.q + self.joint_offsets(ctx)
        R_BF, J_kin = kinematic_rotation_jacobian(self.kinematic, q_eff)
        R_LB = self.T_tracker_base[:3, :3]
        R_LF = R_LB @ R_BF
        N, nk, P = ctx.n, len(self.kinematic.param_names), len(self.param_names)
        J = np.zeros((N, 3, P))
        J[:, :, :nk] = R_LB @ J_kin
        J[:, :, nk + 3 : nk + 6] = R_LB
        start = nk + 6 + 3 * len(self.tools)
        for k, sid in enumerate(sorted(self.probes)):
            rows = np.flatnonzero(smr == sid)
            J[np.ix_(rows, np.arange(3), np.arange(start + 3 * k, start + 3 * k + 3))] = R_LF[rows]
        for eff, sl in zip(self.effects, self.effect_slices(), strict=True):
            if eff.kind == "joint":
                col = J[:, :, self.kinematic.param_names.index(f"theta{eff.joint_index + 1}")]
                J[:, :, sl] = col[:, :, None] * eff.cached_regressors(ctx, self.nominal)[:, None, :]
        return R_LF @ R_FP, J

    def predict_rotation_ctx(self, ctx: EffectContext, smr: np.ndarray) -> np.ndarray:
        """Predicted probe orientations R_tracker_probe (N, 3, 3)."""
        R_FP = self._row_probes(smr)
        q_eff = ctx.q + self.joint_offsets(ctx)
        R_BF = forward_kinematics(self.kinematic, q_eff)[:, :3, :3]
        return np.einsum("ij,njk->nik", self.T_tracker_base[:3, :3], R_BF) @ R_FP

    def predict_rotation(self, df: pd.DataFrame) -> np.ndarray:
        """Predicted probe orientations R_tracker_probe (N, 3, 3) for the joints (and drivers) in df."""
        ctx, _ = self.context(df)
        return self.predict_rotation_ctx(ctx, smr_ids(df))

    # ----- compensation -------------------------------------------------------------------------
    def corrected_joints(
        self,
        targets_tracker: np.ndarray,
        q_seed: np.ndarray | None = None,
        smr: int | None = None,
        iterations: int = 20,
        t_s: np.ndarray | None = None,
        temperature_c: np.ndarray | None = None,
        approach: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Joints to command so that the model puts the SMR at the targets (tracker frame, m).

        Gauss-Newton on the joints from a seed (N, n): the joints the controller would use for the target
        (e.g. its IK of a pose), or by default the calibrated geometry's position IK (`hil.geometry.ik.solve_ik`).
        Position only: 3 equations in 6 joints, so the minimum-norm joint step is taken and the seed's
        orientation is kept to first order. Thermal effects need `t_s` / `temperature_c` (N,) at the
        time of the move; backlash needs `approach` (N, n) signs of the final motion of each joint (0 =
        unknown). Returns (q (N, n), remaining model error (N,) m).
        """
        targets = np.atleast_2d(np.asarray(targets_tracker, float))
        sid = sorted(self.tools)[0] if smr is None else int(smr)
        if q_seed is None:
            p_base = transform_points(invert(self.T_tracker_base), targets)
            q_seed = solve_ik(self.kinematic, p_base, mode="position", p_flange_tool=self.tools[sid]).q
        q = np.atleast_2d(np.asarray(q_seed, float)).copy()
        smr_rows = np.full(len(q), sid)
        tools = self._row_tools(smr_rows)
        theta_cols = [self.kinematic.param_names.index(f"theta{j + 1}") for j in range(q.shape[1])]
        for _ in range(iterations):
            ctx = EffectContext(q, t_s, temperature_c, None, tools, approach)
            p, J = self.jacobian_ctx(ctx, smr_rows)
            Jq = J[:, :, theta_cols]
            err = targets - p
            if np.max(np.linalg.norm(err, axis=1)) < 1e-9:
                break
            JJt = Jq @ np.swapaxes(Jq, 1, 2) + 1e-12 * np.eye(3)
            q = q + np.einsum("nji,nj->ni", Jq, np.linalg.solve(JJt, err[..., None])[..., 0])
        ctx = EffectContext(q, t_s, temperature_c, None, tools, approach)
        return q, np.linalg.norm(targets - self.predict_ctx(ctx), axis=1)

    # ----- persistence --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "robot": self.robot,
            "nominal": model_to_dict(self.nominal),
            "kinematic": model_to_dict(self.kinematic),
            "T_tracker_base": self.T_tracker_base.tolist(),
            "tools_m": {str(k): v.tolist() for k, v in sorted(self.tools.items())},
            "effects": [e.to_dict() for e in self.effects],
            "probes_flange": {str(k): v.tolist() for k, v in sorted(self.probes.items())},
            "residual_map": self.residual_map,
            "info": self.info,
            "spread": None if self.spread is None else self.spread.to_dict(),
        }

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(to_jsonable(self.to_dict()), indent=1, allow_nan=False))

    @classmethod
    def from_dict(cls, data: dict) -> CalibratedModel:
        if data.get("format") not in READABLE_FORMATS:
            raise ValueError(
                f"not a calibrated model file (format {data.get('format')!r}, expected {FORMAT!r})"
            )
        spread = data.get("spread")
        return cls(
            robot=data["robot"],
            nominal=model_from_dict(data["nominal"]),
            kinematic=model_from_dict(data["kinematic"]),
            T_tracker_base=np.asarray(data["T_tracker_base"], float),
            tools={int(k): np.asarray(v, float) for k, v in data["tools_m"].items()},
            effects=[effect_from_dict(e) for e in data.get("effects", [])],
            info=data.get("info", {}),
            residual_map=data.get("residual_map"),
            probes={int(k): np.asarray(v, float) for k, v in data.get("probes_flange", {}).items()},
            spread=None if spread is None else PredictionSpread.from_dict(spread),
            file_format=data["format"],
        )

    @classmethod
    def load(cls, path: str | Path) -> CalibratedModel:
        """Read a model file; a truncated, foreign or damaged file raises ValueError naming it and the cause."""
        path = Path(path)
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            raise ValueError(
                f"{path}: not a model file (binary, not JSON); give a model written by hil"
            ) from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            cause = "truncated" if exc.pos >= len(text.rstrip()) else "not valid JSON"
            raise ValueError(
                f"{path}: {cause} at line {exc.lineno} column {exc.colno} ({exc.msg}); "
                "write the model again with 'hil calibrate -o' or 'hil diagnose -o'"
            ) from None
        if not isinstance(data, dict):
            raise ValueError(
                f"{path}: not a calibrated model file (JSON {type(data).__name__}); give a model file"
            )
        try:
            return cls.from_dict(data)
        except (KeyError, TypeError, ValueError) as exc:
            detail = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
            raise ValueError(
                f"{path}: {detail}; give a model written by 'hil calibrate -o' or 'hil diagnose -o'"
            ) from None


def _context_tools(ctx: EffectContext) -> np.ndarray:
    """The tool point of every row (N, 3), which CalibratedModel.context always sets."""
    if ctx.p_flange_tool is None:
        raise ValueError("the effect context has no tool points: build it with CalibratedModel.context(df)")
    return ctx.p_flange_tool


def model_to_dict(m: KinematicModel) -> dict:
    """KinematicModel -> JSON-ready dict (all fields)."""
    return {
        "name": m.name,
        "theta": list(map(float, m.theta)),
        "d": list(map(float, m.d)),
        "a": list(map(float, m.a)),
        "alpha": list(map(float, m.alpha)),
        "beta": list(map(float, m.beta)),
        "uses_beta": [bool(b) for b in m.uses_beta],
        "joint_limits": np.asarray(m.joint_limits, float).tolist(),
        "T_last_flange": np.asarray(m.T_last_flange, float).tolist(),
        **({} if m.expansion_per_k is None else {"expansion_per_k": float(m.expansion_per_k)}),
        **({} if m.link_masses_kg is None else {"link_masses_kg": [float(v) for v in m.link_masses_kg]}),
    }


def model_from_dict(d: dict) -> KinematicModel:
    return KinematicModel(
        name=d["name"],
        theta=np.asarray(d["theta"], float),
        d=np.asarray(d["d"], float),
        a=np.asarray(d["a"], float),
        alpha=np.asarray(d["alpha"], float),
        beta=np.asarray(d["beta"], float),
        uses_beta=np.asarray(d["uses_beta"], bool),
        joint_limits=np.asarray(d["joint_limits"], float),
        T_last_flange=np.asarray(d["T_last_flange"], float),
        expansion_per_k=d.get("expansion_per_k"),
        link_masses_kg=tuple(map(float, d["link_masses_kg"]))
        if d.get("link_masses_kg") is not None
        else None,
    )


def initial_model(
    robot: str | KinematicModel, df: pd.DataFrame, tool_guess_m: np.ndarray | None = None
) -> CalibratedModel:
    """Nominal geometry, tool points at a guess, base frame from a rigid fit of nominal to measured points."""
    nominal = get_robot(robot) if isinstance(robot, str) else robot
    ids = smr_ids(df)
    guess = np.zeros(3) if tool_guess_m is None else np.asarray(tool_guess_m, float)
    tools = {int(s): guess.copy() for s in np.unique(ids)}
    model = CalibratedModel(nominal.name, nominal, nominal, np.eye(4), tools)
    ctx, _ = model.context(df)
    p_base = model.predict_ctx(ctx)
    T, _ = fit_rigid(p_base, points_m(df))
    return with_initial_probes(replace(model, T_tracker_base=T), df)


def with_initial_probes(model: CalibratedModel, df: pd.DataFrame) -> CalibratedModel:
    """The model with a probe orientation for every nest of a frame with orientation columns that it
    lacks one for: the rotation nearest the mean of R_flange_probe seen from each row (model geometry)."""
    R_meas = orientations(df)
    ids = smr_ids(df)
    lacking = sorted(set(np.unique(ids).tolist()) - set(model.probes))
    if R_meas is None or not lacking:
        return model
    ctx, _ = model.context(df)
    R_BF = forward_kinematics(model.kinematic, ctx.q + model.joint_offsets(ctx))[:, :3, :3]
    seen = np.swapaxes(R_BF, 1, 2) @ model.T_tracker_base[:3, :3].T @ R_meas
    probes = dict(model.probes)
    for s in lacking:
        U, _, Vt = np.linalg.svd(seen[ids == s].mean(axis=0))
        probes[int(s)] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return replace(model, probes=probes)
