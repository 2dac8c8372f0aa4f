"""Residual maps: what the parametric model still gets wrong, interpolated from measured points.

- ``idw``: inverse-distance weighting over the 8 vertices of the grid cube holding the target
  (grid paper, methods.md 2c; power 2; a target on a vertex takes that vertex's residual). The grid's own
  frame (any rotation, a step per axis) is recovered from the measured points (hil.model.grid_frame):
  the planner turns its box to face the tracker, and a foreign campaign records no grid frame.
- ``svr``: RBF-kernel support-vector regressors per axis on the six joint angles (SVR paper, methods.md 3:
  kernel width sigma = 2 rad -> gamma = 1/(2 sigma^2)), in two modes. "global" (ours): one model over the
  volume on the residual after calibration; targets in units of the noise sigma, epsilon = 0.5 sigma, and C
  by 3-fold cross-validation from 0.1 ... 100: the paper's C = 100 and epsilon = 0.2 mm suit errors of
  millimetres, not residuals near the noise floor. "per_cube" (the paper's): one model per cube on the raw
  error against the nominal model, C = 100, epsilon = 0.2 mm (hil.analysis.calibration.cube_svr).
- ``gp``: a Gaussian process on the six joint angles (constant x RBF + white noise, hyper-parameters by
  marginal likelihood), all three axes together.

Maps are fitted with scikit-learn but store plain arrays and predict with numpy, so a calibrated model
file can carry them. `outside` flags targets beyond the measured volume.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree

from hil.model.grid_frame import GridFrame, estimate_grid_frame, location_spacing

MAP_KINDS: tuple[str, ...] = ("idw", "svr", "gp")


class ResidualMap:
    kind = ""

    def __init__(self, state: dict | None = None) -> None:
        self.state = state or {}

    def fit(
        self, q: np.ndarray, p_base: np.ndarray, residual: np.ndarray, noise_sigma_m: float
    ) -> ResidualMap:
        raise NotImplementedError

    def predict_raw(self, q: np.ndarray, p_base: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def predict(self, q: np.ndarray, p_base: np.ndarray, warn: bool = True) -> np.ndarray:
        """Predicted residual (N, 3), m; warns when a target lies outside the measured volume."""
        out = self.outside(p_base)
        if warn and np.any(out):
            warnings.warn(
                f"{int(out.sum())} target(s) lie outside the measured volume; the {self.kind} residual map "
                "extrapolates there (rows " + ", ".join(map(str, np.flatnonzero(out)[:10])) + ")",
                stacklevel=2,
            )
        return self.predict_raw(q, p_base)

    def _remember_volume(self, p_base: np.ndarray) -> None:
        spacing = location_spacing(p_base)  # nearest other location: repeated orientations don't count
        self.state["volume"] = {
            "lo": p_base.min(axis=0).tolist(),
            "hi": p_base.max(axis=0).tolist(),
            "points": p_base.tolist(),
            "spacing": spacing,
        }

    def outside(self, p_base: np.ndarray) -> np.ndarray:
        """(N,) True where a target is beyond the measured box or far from every measured point."""
        vol = self.state["volume"]
        lo, hi, spacing = np.array(vol["lo"]), np.array(vol["hi"]), vol["spacing"]
        pts = np.asarray(vol["points"])
        margin = 0.5 * spacing
        box = np.any((p_base < lo - margin) | (p_base > hi + margin), axis=1)
        nearest = cKDTree(pts).query(p_base)[0]
        return box | (nearest > 2.0 * spacing)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "state": self.state}

    def describe(self) -> str:
        """What the map is and what it was trained on, for reports."""
        return self.kind


class IDWGridMap(ResidualMap):
    kind = "idw"

    def __init__(self, state: dict | None = None, step_m: float | None = None, power: float = 2.0) -> None:
        super().__init__(state)
        self.step_m = step_m
        self.power = power

    def fit(self, q, p_base, residual, noise_sigma_m):
        self._remember_volume(p_base)
        frame = estimate_grid_frame(p_base, self.step_m)
        idx, on_grid = frame.vertices(p_base)
        if not on_grid.any():
            raise ValueError("no grid vertex found among the points: the IDW map needs a grid campaign")
        vertices: dict[tuple, list] = {}
        for k, r in zip(map(tuple, idx[on_grid]), residual[on_grid], strict=True):
            vertices.setdefault(k, []).append(r)  # several orientations at one vertex are averaged
        keys = sorted(vertices)
        self.state.update(
            {
                **frame.to_dict(),
                "power": self.power,
                "vertex_index": [list(k) for k in keys],
                "vertex_residual_m": [np.mean(vertices[k], axis=0).tolist() for k in keys],
            }
        )
        return self

    def describe(self) -> str:
        steps = " x ".join(f"{s * 1e3:.0f}" for s in self.frame().steps_m)
        return (
            f"IDW over the 8 vertices of the grid cube, {len(self.state['vertex_index'])} vertices, grid frame "
            f"recovered from the points (steps {steps} mm), on the residual after the kinematic calibration"
        )

    def frame(self) -> GridFrame:
        """The grid's frame; a map saved before grids had one is axis-aligned with one step."""
        st = self.state
        steps = st.get("steps_m", [st.get("step_m", 0.1)] * 3)
        return GridFrame(
            np.asarray(st.get("R_base_grid", np.eye(3)), float),
            np.asarray(st["origin_m"]),
            np.asarray(steps, float),
        )

    def predict_raw(self, q, p_base):
        st = self.state
        frame, power = self.frame(), st["power"]
        keys = np.array(st["vertex_index"], dtype=int)
        vals = np.array(st["vertex_residual_m"])
        lo = keys.min(axis=0)
        shape = keys.max(axis=0) - lo + 1
        table = np.zeros((*shape, 3))
        have = np.zeros(shape, bool)
        table[tuple((keys - lo).T)] = vals
        have[tuple((keys - lo).T)] = True
        u = frame.lattice(p_base)
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        idx = np.floor(u).astype(int)[:, None, :] + corners[None]  # (N, 8, 3) cube vertices
        inside = np.all((idx >= lo) & (idx < lo + shape), axis=2)
        cl = np.clip(idx - lo, 0, shape - 1)
        present = inside & have[cl[..., 0], cl[..., 1], cl[..., 2]]
        corner_vals = table[cl[..., 0], cl[..., 1], cl[..., 2]]  # (N, 8, 3)
        d = np.linalg.norm((u[:, None, :] - idx) * frame.steps_m, axis=2)
        # (1/d)^m over the measured vertices; a target on a vertex takes that vertex's residual.
        w = np.where(present, 1.0 / np.maximum(d, 1e-12) ** power, 0.0)
        out = np.einsum("nk,nkc->nc", w, corner_vals) / np.maximum(w.sum(axis=1), 1e-300)[:, None]
        on_vertex = present & (d < 1e-9)
        hit = on_vertex.any(axis=1)
        out[hit] = corner_vals[hit, np.argmax(on_vertex[hit], axis=1)]
        lonely = ~present.any(axis=1)  # no vertex of this cube was measured: the nearest measured vertex
        if np.any(lonely):
            gap = (u[lonely][:, None] - keys[None]) * frame.steps_m
            out[lonely] = vals[np.argmin(np.linalg.norm(gap, axis=2), axis=1)]
        return out


SVR_MODES: dict[str, str] = {
    "global": "one model over the whole volume, on the residual after the kinematic calibration (ours)",
    "per_cube": "one model per cube, on the raw error against the nominal model (the SVR paper)",
}
PAPER_SVR = {
    "C": 100.0,
    "epsilon_m": 0.2e-3,
    "sigma_rad": 2.0,
}  # methods.md 3: C = 100, eps = 0.2 mm, sigma = 2


def _fit_axes(q: np.ndarray, y: np.ndarray, C: float, gamma: float, epsilon: float) -> list[dict]:
    """One RBF-kernel SVR per axis of `y` (N, 3) on the joints, as plain arrays."""
    from sklearn.svm import SVR

    axes = []
    for k in range(3):
        svr = SVR(kernel="rbf", C=C, gamma=gamma, epsilon=epsilon).fit(q, y[:, k])
        axes.append(
            {
                "support": svr.support_vectors_.tolist(),
                "dual": svr.dual_coef_[0].tolist(),
                "intercept": float(svr.intercept_[0]),
            }
        )
    return axes


def _predict_axes(axes: list[dict], gamma: float, q: np.ndarray) -> np.ndarray:
    """(N, 3) from the per-axis support vectors, dual coefficients and intercepts."""
    out = np.zeros((len(q), 3))
    for k, ax in enumerate(axes):
        sv = np.asarray(ax["support"])
        if sv.size == 0:
            out[:, k] = ax["intercept"]
            continue
        K = np.exp(-gamma * np.sum((q[:, None] - sv[None]) ** 2, axis=2))
        out[:, k] = K @ np.asarray(ax["dual"]) + ax["intercept"]
    return out


class SVRMap(ResidualMap):
    """SVR on the six joint angles, in one of two modes (SVR_MODES).

    "global" (ours, used by the diagnosis): one model per axis over the whole volume, fitted to the residual
    the kinematic calibration leaves; targets in noise sigmas, C by cross-validation. "per_cube" (the SVR
    paper): the volume cut into cubes of `cube_m` on a lattice through the base origin, one model per cube
    with the paper's C = 100, epsilon = 0.2 mm, sigma = 2; the cube holding the target picks the model. The
    paper fits the raw error against the nominal model: hil.analysis.calibration.cube_svr builds that model.
    """

    kind = "svr"

    def __init__(
        self,
        state: dict | None = None,
        C: float | None = None,
        sigma_rad: float = 2.0,
        mode: str = "global",
        cube_m: float = 0.1,
    ) -> None:
        super().__init__(state)
        if mode not in SVR_MODES:
            raise ValueError(f"SVR mode '{mode}': use one of {', '.join(SVR_MODES)}")
        self.C, self.gamma, self.mode, self.cube_m = C, 1.0 / (2.0 * sigma_rad**2), mode, cube_m

    def describe(self) -> str:
        mode = self.state.get("mode", "global")
        size = f" of {self.state['cube_m'] * 1e3:g} mm" if mode == "per_cube" else ""
        return f"SVR, {SVR_MODES[mode].replace('per cube', 'per cube' + size)}"

    def fit(self, q, p_base, residual, noise_sigma_m):
        self._remember_volume(p_base)
        if self.mode == "per_cube":
            return self._fit_per_cube(q, p_base, residual)
        scale = 1.0 / max(noise_sigma_m, 1e-12)  # targets in units of the noise sigma
        y = residual * scale
        C = self.C if self.C is not None else self._choose_C(q, y)
        axes = _fit_axes(q, y, C, self.gamma, 0.5)
        self.state.update({"mode": "global", "gamma": self.gamma, "scale": scale, "C": C, "axes": axes})
        return self

    def _fit_per_cube(self, q: np.ndarray, p_base: np.ndarray, error: np.ndarray) -> SVRMap:
        """The paper's models: one per cube holding at least two points, targets in mm."""
        scale = 1e3
        C = self.C if self.C is not None else PAPER_SVR["C"]
        cube = self.cube_index(p_base)
        keys, label = np.unique(cube, axis=0, return_inverse=True)
        label = label.ravel()
        cubes = []
        for c, key in enumerate(keys):
            rows = label == c
            if rows.sum() < 2:
                continue
            axes = _fit_axes(q[rows], error[rows] * scale, C, self.gamma, PAPER_SVR["epsilon_m"] * scale)
            cubes.append({"cube": key.tolist(), "points": int(rows.sum()), "axes": axes})
        if not cubes:
            raise ValueError("no cube holds two training points: give more points or larger cubes")
        self.state.update(
            {
                "mode": "per_cube",
                "cube_m": self.cube_m,
                "gamma": self.gamma,
                "scale": scale,
                "C": C,
                "cubes": cubes,
            }
        )
        return self

    def cube_index(self, p_base: np.ndarray) -> np.ndarray:
        """Integer cube (N, 3) of each point: cubes of `cube_m` on a lattice through the base origin."""
        size = self.state.get("cube_m", self.cube_m)
        return np.floor(np.asarray(p_base, float) / size).astype(int)

    def _choose_C(self, q: np.ndarray, y: np.ndarray) -> float:
        """C by 3-fold cross-validation: the paper's C = 100 suits mm-sized errors, not residuals at noise."""
        from sklearn.svm import SVR

        if len(q) > MAP_TUNE_ROWS:  # C from a subset: each SVR costs the square of its rows
            keep = np.sort(np.random.default_rng(0).permutation(len(q))[:MAP_TUNE_ROWS])
            q, y = q[keep], y[keep]
        folds = np.array_split(np.random.default_rng(0).permutation(len(q)), 3)
        best, best_err = 100.0, np.inf
        for C in (0.1, 1.0, 10.0, 100.0):
            err = 0.0
            for test in folds:
                train = np.setdiff1d(np.arange(len(q)), test)
                for k in range(3):
                    svr = SVR(kernel="rbf", C=C, gamma=self.gamma, epsilon=0.5).fit(q[train], y[train, k])
                    err += float(np.sum((svr.predict(q[test]) - y[test, k]) ** 2))
            if err < best_err:
                best, best_err = C, err
        return best

    def predict_raw(self, q, p_base):
        st = self.state
        if st.get("mode", "global") == "global":
            return _predict_axes(st["axes"], st["gamma"], q) / st["scale"]
        # The cube holding the target picks the model; a cube without one: the nearest trained cube.
        keys = np.array([c["cube"] for c in st["cubes"]])
        cube = self.cube_index(p_base)
        pick = np.argmin(np.sum((cube[:, None, :] - keys[None]) ** 2, axis=2), axis=1)
        out = np.zeros((len(q), 3))
        for c in np.unique(pick):
            rows = pick == c
            out[rows] = _predict_axes(st["cubes"][c]["axes"], st["gamma"], q[rows])
        return out / st["scale"]


# What each kind is and is trained on when the diagnosis fits it: the report prints it beside the kind.
MAP_MODES: dict[str, str] = {
    "idw": "IDW on the grid cube's 8 vertices (grid frame from the points), on the residual after calibration",
    "svr": "SVR, " + SVR_MODES["global"],
    "gp": "Gaussian process on the joint angles, on the residual after calibration",
}


class GPMap(ResidualMap):
    kind = "gp"

    def describe(self) -> str:
        return "Gaussian process on the joint angles, on the residual after the kinematic calibration"

    def __init__(self, state: dict | None = None, hyper: dict | None = None) -> None:
        super().__init__(state)
        self.hyper = hyper  # fixed hyper-parameters (amplitude, length_scale, noise): no optimisation

    def fit(self, q, p_base, residual, noise_sigma_m):
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

        self._remember_volume(p_base)
        scale = 1000.0
        h = self.hyper or {
            "amplitude": 0.01,
            "length_scale": 1.0,
            "noise": max((noise_sigma_m * scale) ** 2, 1e-8),
        }
        kernel = ConstantKernel(h["amplitude"], (1e-8, 1e2)) * RBF(
            h["length_scale"], (0.05, 20.0)
        ) + WhiteKernel(h["noise"], (1e-10, 1e1))
        gp = GaussianProcessRegressor(
            kernel=kernel,
            normalize_y=False,
            optimizer=None if self.hyper else "fmin_l_bfgs_b",
            random_state=0,
        )
        mean = residual.mean(axis=0) * scale
        if self.hyper is None and len(q) > MAP_TUNE_ROWS:  # hyper-parameters on a subset, then fixed
            h = GPMap().fit(*_tuning_rows(q, p_base, residual), noise_sigma_m).state
            return GPMap(self.state, {k: h[k] for k in ("amplitude", "length_scale", "noise")}).fit(
                q, p_base, residual, noise_sigma_m
            )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gp.fit(q, residual * scale - mean)
        k = gp.kernel_
        self.state.update(
            {
                "X": q.tolist(),
                "alpha": np.asarray(gp.alpha_).reshape(len(q), -1).tolist(),
                "amplitude": float(k.k1.k1.constant_value),
                "length_scale": float(k.k1.k2.length_scale),
                "noise": float(k.k2.noise_level),
                "mean": mean.tolist(),
                "scale": scale,
            }
        )
        return self

    def predict_raw(self, q, p_base):
        st = self.state
        X = np.asarray(st["X"])
        d2 = np.sum((q[:, None] - X[None]) ** 2, axis=2)
        K = st["amplitude"] * np.exp(-0.5 * d2 / st["length_scale"] ** 2)
        return (K @ np.asarray(st["alpha"]) + np.asarray(st["mean"])) / st["scale"]


# Beyond this many rows a map's hyper-parameters (the GP's kernel, the SVR's C) are chosen on a fixed random
# subset of this size and then fixed for the fit on every row: the marginal likelihood's optimiser costs
# the cube of the rows per step (minutes and a gigabyte at 3000 rows), and 600 points pin three
# hyper-parameters (and keep a 12 000-pose diagnosis within two minutes).
MAP_TUNE_ROWS = 600


def _tuning_rows(q: np.ndarray, p_base: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, ...]:
    """The fixed random subset of MAP_TUNE_ROWS rows the hyper-parameters are chosen on."""
    keep = np.sort(np.random.default_rng(0).permutation(len(q))[:MAP_TUNE_ROWS])
    return q[keep], p_base[keep], residual[keep]


_CLASSES = {c.kind: c for c in (IDWGridMap, SVRMap, GPMap)}


def make_map(kind: str) -> ResidualMap:
    if kind not in _CLASSES:
        raise ValueError(f"unknown residual map '{kind}'; choose one of {', '.join(MAP_KINDS)}")
    return _CLASSES[kind]()


def map_from_dict(data: dict) -> ResidualMap:
    m = make_map(data["kind"])
    m.state = data["state"]
    if isinstance(m, SVRMap):
        m.gamma = m.state.get("gamma", m.gamma)
        m.mode = m.state.get("mode", "global")
        m.cube_m = m.state.get("cube_m", m.cube_m)
    return m


def kfold_map_errors(
    kind: str,
    q: np.ndarray,
    p_base: np.ndarray,
    residual: np.ndarray,
    noise_sigma_m: float,
    folds: list[np.ndarray],
) -> np.ndarray:
    """Held-out corrected residuals (N, 3): residual minus the map fitted on the other folds."""
    out = np.zeros_like(residual)
    n = len(q)
    hyper = None
    if kind == "gp":  # hyper-parameters once on all rows, then fixed in the folds (cheap, and stable)
        st = GPMap().fit(q, p_base, residual, noise_sigma_m).state
        hyper = {k: st[k] for k in ("amplitude", "length_scale", "noise")}
    for test in folds:
        train = np.setdiff1d(np.arange(n), test)
        m = GPMap(hyper=hyper) if kind == "gp" else make_map(kind)
        m.fit(q[train], p_base[train], residual[train], noise_sigma_m)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[test] = residual[test] - m.predict_raw(q[test], p_base[test])
    return out
