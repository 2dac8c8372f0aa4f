"""ISO 9283 performance figures: pose accuracy and repeatability, distance accuracy, path accuracy.

The standard's test: a cube in the working volume, five poses on one of its diagonal planes (P1 at the
centre, P2..P5 on the plane's diagonals, 10 % of a diagonal from its corner), n cycles approaching each
pose from one direction. Per pose with commanded position c and attained positions x_i (i = 1..n):
barycentre x̄; AP = |x̄ - c| (and its x, y, z parts x̄ - c); l_i = |x_i - x̄|, RP = l̄ + 3 S_l with S_l the
sample standard deviation of l (n - 1). Orientation: AP_a = mean(a_i) - a_c, RP_a = 3 S_a (per angle).
Distance P2-P4: AD = mean(D_i) - D_c, RD = 3 S_D. Path: at each commanded point, in the plane normal to the
commanded path, the attained paths' crossings x_ij and their barycentre G_j: AT = max_j |G_j - c_j|,
RT = max_j (l̄_j + 3 S_lj). All inputs and outputs in SI (metres, radians); mm and degrees at the edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from hil.data.dataset import (
    CMD_ORIENTATION_COLUMNS,
    CMD_POSITION_COLUMNS,
    ORIENTATION_COLUMNS,
    POSITION_COLUMNS,
    angles_rad,
    commanded_points_m,
    points_m,
)

POSE_LABELS: tuple[str, ...] = ("P1", "P2", "P3", "P4", "P5")
CORNER_FRACTION = 0.1  # P2..P5 lie this fraction of the diagonal's length in from their corners
CMD_SPREAD_M = 1e-6  # one pose's commanded position may vary this much between its rows (export rounding)
DISTANCE_POSES = ("P2", "P4")


class Iso9283Error(ValueError):
    """A campaign the standard's formulas cannot be applied to; the message says what to fix."""


def cube_poses(centre_m: np.ndarray, side_m: float, R_cube: np.ndarray | None = None) -> np.ndarray:
    """The five measurement positions (5, 3) of a cube with this centre and side, in the cube's frame's parent.

    The plane used is the diagonal plane through the cube's edges (-,-,*) and (+,+,*) of its own axes
    (`R_cube` columns; default the parent's axes): a rectangle of width side*sqrt(2) and height side.
    Its corners C1..C4 go round the rectangle, so P2 and P4 (and P3 and P5) sit on opposite corners.
    """
    if not side_m > 0:
        raise Iso9283Error(f"the test cube's side must be positive, got {side_m * 1e3:g} mm")
    R = np.eye(3) if R_cube is None else np.asarray(R_cube, float)
    h = 0.5 * side_m
    corners_cube = np.array([[-h, -h, -h], [h, h, -h], [h, h, h], [-h, -h, h]])
    inward = CORNER_FRACTION * (-2.0 * corners_cube)  # towards the opposite corner, 10 % of the diagonal
    local = np.vstack([np.zeros(3), corners_cube + inward])
    return np.asarray(centre_m, float) + local @ R.T


@dataclass(frozen=True)
class PoseFigures:
    """One pose's figures (SI): accuracy vector and norm, repeatability, and their ingredients."""

    pose: str
    cycles: int
    commanded_m: np.ndarray  # (3,)
    barycentre_m: np.ndarray  # (3,)
    AP_m: float
    AP_xyz_m: np.ndarray  # (3,) barycentre - commanded
    RP_m: float
    l_mean_m: float
    S_l_m: float
    AP_abc_rad: np.ndarray | None = None  # (3,) mean attained - commanded angle
    RP_abc_rad: np.ndarray | None = None  # (3,) 3 S per angle

    def to_dict(self) -> dict:
        """The pose's figures in the report's units (mm, deg)."""
        out: dict = {
            "pose": self.pose,
            "cycles": self.cycles,
            "AP_mm": self.AP_m * 1e3,
            "AP_x_mm": float(self.AP_xyz_m[0] * 1e3),
            "AP_y_mm": float(self.AP_xyz_m[1] * 1e3),
            "AP_z_mm": float(self.AP_xyz_m[2] * 1e3),
            "RP_mm": self.RP_m * 1e3,
            "l_mean_mm": self.l_mean_m * 1e3,
            "S_l_mm": self.S_l_m * 1e3,
            "commanded_mm": (self.commanded_m * 1e3).tolist(),
            "barycentre_mm": (self.barycentre_m * 1e3).tolist(),
        }
        if self.AP_abc_rad is not None and self.RP_abc_rad is not None:
            for k, name in enumerate("abc"):
                out[f"AP_{name}_deg"] = float(np.rad2deg(self.AP_abc_rad[k]))
                out[f"RP_{name}_deg"] = float(np.rad2deg(self.RP_abc_rad[k]))
        return out


def pose_figures(
    pose: str,
    attained_m: np.ndarray,
    commanded_m: np.ndarray,
    attained_rad: np.ndarray | None = None,
    commanded_rad: np.ndarray | None = None,
) -> PoseFigures:
    """AP and RP of one pose from its n attained positions (n, 3) and its commanded position (3,)."""
    x = np.asarray(attained_m, float)
    n = len(x)
    if n < 2:
        raise Iso9283Error(
            f"pose {pose} has {n} cycle; repeatability needs at least 2 (the standard uses 30): measure more cycles"
        )
    c = np.asarray(commanded_m, float)
    bary = x.mean(axis=0)
    l = np.linalg.norm(x - bary, axis=1)
    S_l = float(np.std(l, ddof=1))
    ap_abc = rp_abc = None
    if attained_rad is not None and commanded_rad is not None:
        # angle errors wrapped to (-pi, pi] before averaging, so a pose near +-180 deg is not torn apart
        err = np.angle(np.exp(1j * (np.asarray(attained_rad, float) - np.asarray(commanded_rad, float))))
        ap_abc = err.mean(axis=0)
        rp_abc = 3.0 * np.std(err, axis=0, ddof=1)
    return PoseFigures(
        pose, n, c, bary, float(np.linalg.norm(bary - c)), bary - c, float(l.mean() + 3.0 * S_l),
        float(l.mean()), S_l, ap_abc, rp_abc,
    )  # fmt: skip


@dataclass(frozen=True)
class DistanceFigures:
    """Distance accuracy and repeatability between two poses (SI)."""

    poses: tuple[str, str]
    cycles: int
    commanded_m: float
    mean_m: float
    AD_m: float
    RD_m: float

    def to_dict(self) -> dict:
        return {
            "poses": list(self.poses),
            "cycles": self.cycles,
            "D_cmd_mm": self.commanded_m * 1e3,
            "D_mean_mm": self.mean_m * 1e3,
            "AD_mm": self.AD_m * 1e3,
            "RD_mm": self.RD_m * 1e3,
        }


def distance_figures(
    poses: tuple[str, str], a_m: np.ndarray, b_m: np.ndarray, a_cmd_m: np.ndarray, b_cmd_m: np.ndarray
) -> DistanceFigures:
    """AD and RD from the attained positions of two poses in the same cycles (n, 3) each."""
    D = np.linalg.norm(np.asarray(a_m, float) - np.asarray(b_m, float), axis=1)
    if len(D) < 2:
        raise Iso9283Error(
            f"poses {poses[0]} and {poses[1]} share {len(D)} cycle; distance repeatability needs at least 2"
        )
    D_c = float(np.linalg.norm(np.asarray(a_cmd_m, float) - np.asarray(b_cmd_m, float)))
    return DistanceFigures(
        poses, len(D), D_c, float(D.mean()), float(D.mean() - D_c), float(3.0 * np.std(D, ddof=1))
    )


@dataclass(frozen=True)
class Iso9283Report:
    """Every pose's figures, the distance figures (None without P2 and P4) and which SMR was used."""

    poses: list[PoseFigures]
    distance: DistanceFigures | None
    smr: int | None = None

    def to_dict(self) -> dict:
        return {
            "standard": "ISO 9283:1998",
            "smr": self.smr,
            "poses": {p.pose: p.to_dict() for p in self.poses},
            "distance": None if self.distance is None else self.distance.to_dict(),
        }

    def table(self, title: str = "ISO 9283 pose performance") -> str:
        """The report's table, in the standard's terms (mm, deg)."""
        return report_table({title: self})


def report_table(reports: dict[str, Iso9283Report]) -> str:
    """One table for one or several runs (e.g. before / after compensation): a block per run."""
    lines = []
    for title, rep in reports.items():
        has_abc = any(p.AP_abc_rad is not None for p in rep.poses)
        head = f"{'pose':<6}{'n':>4}{'AP':>9}{'AP_x':>9}{'AP_y':>9}{'AP_z':>9}{'RP':>9}  mm"
        if has_abc:
            head += f"{'AP_a':>9}{'AP_b':>9}{'AP_c':>9}{'RP_a':>8}{'RP_b':>8}{'RP_c':>8}  deg"
        lines += [f"{title}" + (f" (SMR {rep.smr})" if rep.smr is not None else ""), head]
        for p in rep.poses:
            line = f"{p.pose:<6}{p.cycles:>4}{p.AP_m * 1e3:9.4f}" + "".join(
                f"{v * 1e3:9.4f}" for v in p.AP_xyz_m
            )
            line += f"{p.RP_m * 1e3:9.4f}"
            if has_abc and p.AP_abc_rad is not None and p.RP_abc_rad is not None:
                line += "    " + "".join(f"{np.rad2deg(v):9.4f}" for v in p.AP_abc_rad)
                line += "".join(f"{np.rad2deg(v):8.4f}" for v in p.RP_abc_rad)
            lines.append(line)
        d = rep.distance
        if d is not None:
            lines.append(
                f"distance {d.poses[0]}-{d.poses[1]}: commanded {d.commanded_m * 1e3:.3f} mm, "
                f"AD {d.AD_m * 1e3:+.4f} mm, RD {d.RD_m * 1e3:.4f} mm ({d.cycles} cycles)"
            )
        lines.append("")
    return "\n".join(lines).rstrip()


def _require(df: pd.DataFrame, columns: tuple[str, ...] | list[str], source: str, why: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise Iso9283Error(f"{source}: missing column(s) {', '.join(missing)} ({why}); add them")


def pose_performance(df: pd.DataFrame, source: str = "campaign", smr: int | None = None) -> Iso9283Report:
    """The ISO 9283 pose figures of a campaign: dataset columns plus `pose`, `cycle` and the commanded
    position x_cmd_mm, y_cmd_mm, z_cmd_mm (tracker frame); with rx/ry/rz_deg and rx/ry/rz_cmd_deg the
    orientation figures too. Several SMRs per pose: one is used (`smr`, default the lowest id)."""
    _require(df, list(POSITION_COLUMNS), source, "the attained positions, tracker frame")
    _require(df, ["pose", "cycle"], source, "which of the five poses and which cycle each row is")
    _require(df, CMD_POSITION_COLUMNS, source, "the commanded position in the tracker frame")
    data = df
    used_smr = None
    if "smr" in df.columns:
        ids = np.unique(df["smr"].to_numpy(int))
        used_smr = int(ids.min()) if smr is None else int(smr)
        if used_smr not in ids:
            raise Iso9283Error(
                f"{source}: no rows of SMR {used_smr}; the campaign holds SMR(s) {', '.join(map(str, ids))}"
            )
        data = df[df["smr"].to_numpy(int) == used_smr]
    cycle = pd.to_numeric(data["cycle"], errors="coerce").to_numpy(float)
    cmd = commanded_points_m(data)
    bad = ~np.isfinite(cycle) | ~np.all(np.isfinite(cmd), axis=1)
    if bad.any():
        raise Iso9283Error(
            f"{source}: a missing or non-numeric cycle or commanded position in {int(bad.sum())} row(s); fill them"
        )
    label = data["pose"].astype(str).str.strip().to_numpy()
    key = pd.Series(list(zip(label, cycle, strict=True)))
    if key.duplicated().any():
        p, c = key[key.duplicated()].iloc[0]
        raise Iso9283Error(
            f"{source}: pose {p} cycle {c:g} appears twice; give each pose one row per cycle (and per SMR)"
        )
    x = points_m(data)
    has_abc = all(c in data.columns for c in (*ORIENTATION_COLUMNS, *CMD_ORIENTATION_COLUMNS))
    abc = angles_rad(data) if has_abc else None
    abc_cmd = angles_rad(data, CMD_ORIENTATION_COLUMNS) if has_abc else None
    order = sorted(
        set(label), key=lambda s: (s not in POSE_LABELS, POSE_LABELS.index(s) if s in POSE_LABELS else 0, s)
    )
    figures = []
    for p in order:
        rows = np.flatnonzero(label == p)
        spread = np.ptp(cmd[rows], axis=0).max()
        if spread > CMD_SPREAD_M:
            raise Iso9283Error(
                f"{source}: pose {p} is commanded at positions {spread * 1e3:.4f} mm apart; every cycle of a "
                "pose must command the same position (check the pose labels)"
            )
        figures.append(
            pose_figures(
                p, x[rows], cmd[rows].mean(axis=0),
                None if abc is None else abc[rows], None if abc_cmd is None else abc_cmd[rows].mean(axis=0),
            )
        )  # fmt: skip
    distance = None
    a, b = DISTANCE_POSES
    if a in order and b in order:
        ra, rb = np.flatnonzero(label == a), np.flatnonzero(label == b)
        common, ia, ib = np.intersect1d(cycle[ra], cycle[rb], return_indices=True)
        distance = distance_figures((a, b), x[ra][ia], x[rb][ib], cmd[ra].mean(axis=0), cmd[rb].mean(axis=0))
    return Iso9283Report(figures, distance, used_smr)


# ------------------------------------------------------------------------------------------ path accuracy
@dataclass(frozen=True)
class PathFigures:
    """Path accuracy AT and repeatability RT (SI) over the commanded points, and where the largest are."""

    runs: int
    points: int
    AT_m: float
    RT_m: float
    AT_along_m: np.ndarray  # (M,) |G_j - c_j| at each commanded point
    RT_along_m: np.ndarray  # (M,) l̄_j + 3 S_lj

    def to_dict(self) -> dict:
        return {
            "runs": self.runs,
            "commanded_points": self.points,
            "AT_mm": self.AT_m * 1e3,
            "RT_mm": self.RT_m * 1e3,
            "AT_worst_point": int(np.argmax(self.AT_along_m)),
            "RT_worst_point": int(np.argmax(self.RT_along_m)),
        }


def commanded_tangents(commanded_m: np.ndarray) -> np.ndarray:
    """Unit tangents (M, 3) of a commanded polyline (central differences, one-sided at the ends)."""
    c = np.asarray(commanded_m, float)
    if len(c) < 2:
        raise Iso9283Error("a commanded path needs at least 2 points")
    t = np.gradient(c, axis=0)
    norm = np.linalg.norm(t, axis=1)
    if np.any(norm < 1e-12):
        raise Iso9283Error("the commanded path repeats a point; give distinct points along it")
    return t / norm[:, None]


def crossings(run_m: np.ndarray, commanded_m: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Where an attained path (K, 3) crosses the plane normal to the commanded path at each commanded point:
    (M, 3), linear between samples; of several crossings the one nearest the commanded point; NaN if none."""
    p = np.asarray(run_m, float)
    s = np.einsum("mk,mk->m", tangents, commanded_m)[:, None]
    h = tangents @ p.T - s  # (M, K) signed distance of every sample from every normal plane
    h0, h1 = h[:, :-1], h[:, 1:]
    cross = (h0 * h1 <= 0) & (h0 != h1)
    w = np.where(cross, h0 / np.where(h0 != h1, h0 - h1, 1.0), 0.0)  # fraction along the segment
    pts = p[:-1][None] + w[..., None] * (p[1:] - p[:-1])[None]  # (M, K-1, 3)
    dist = np.where(cross, np.linalg.norm(pts - commanded_m[:, None], axis=2), np.inf)
    k = np.argmin(dist, axis=1)
    out = pts[np.arange(len(k)), k]
    out[~np.isfinite(dist[np.arange(len(k)), k])] = np.nan
    return out


def path_performance(commanded_m: np.ndarray, runs_m: list[np.ndarray]) -> PathFigures:
    """AT and RT of n attained paths (each (K_i, 3), in time order) against a commanded polyline (M, 3)."""
    if len(runs_m) < 2:
        raise Iso9283Error(f"path repeatability needs at least 2 runs, got {len(runs_m)}; record more runs")
    c = np.asarray(commanded_m, float)
    t = commanded_tangents(c)
    x = np.stack([crossings(r, c, t) for r in runs_m])  # (n, M, 3)
    covered = np.all(np.isfinite(x[..., 0]), axis=0)
    if not covered.any():
        raise Iso9283Error("no attained path crosses the commanded path's normal planes; check the frames")
    x, c = x[:, covered], c[covered]
    G = x.mean(axis=0)
    at = np.linalg.norm(G - c, axis=1)
    l = np.linalg.norm(x - G[None], axis=2)
    rt = l.mean(axis=0) + 3.0 * np.std(l, axis=0, ddof=1)
    return PathFigures(len(runs_m), int(covered.sum()), float(at.max()), float(rt.max()), at, rt)


def path_campaign_figures(df: pd.DataFrame, source: str = "paths") -> dict[str, PathFigures]:
    """AT / RT per path of a path campaign: rows of columns `path`, `run`, attained x_mm, y_mm, z_mm and the
    commanded point at the same instant x_cmd_mm, y_cmd_mm, z_cmd_mm, in time order. The commanded polyline
    of a path is its first run's commanded points."""
    _require(df, ["path", "run"], source, "which path and which run each sample belongs to")
    _require(df, [*POSITION_COLUMNS, *CMD_POSITION_COLUMNS], source, "attained and commanded points")
    out = {}
    for name, rows in df.groupby(df["path"].astype(str), sort=False):
        runs = [points_m(g) for _, g in rows.groupby("run", sort=True)]
        first = rows[rows["run"] == rows["run"].min()]
        commanded = commanded_points_m(first)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(commanded, axis=0), axis=1) > 1e-9])
        try:
            out[str(name)] = path_performance(commanded[keep], runs)
        except Iso9283Error as exc:
            raise Iso9283Error(f"{source}: path {name}: {exc}") from None
    return out


def commanded_along(commanded_m: np.ndarray, samples_m: np.ndarray, lookahead: int = 2) -> np.ndarray:
    """The commanded point (K, 3) each attained sample (K, 3, in time order) stands at: its foot on the
    commanded polyline (M, 3), searched forward only (the segment of the sample before, or one of the next
    `lookahead`), and never behind the sample before along the path. So a closed path's start and end stay
    apart, and samples taken at rest (noise around one point) give one commanded point, not a zigzag."""
    c = np.asarray(commanded_m, float)
    x = np.asarray(samples_m, float)
    if len(c) < 2:
        raise Iso9283Error("a commanded path needs at least 2 points")
    a, d = c[:-1], np.diff(c, axis=0)  # segments a + t d, t in [0, 1]
    length = np.linalg.norm(d, axis=1)
    if np.any(length < 1e-12):
        raise Iso9283Error("the commanded path repeats a point; give distinct points along it")
    t = np.clip(np.einsum("ksj,sj->ks", x[:, None, :] - a[None], d) / length**2, 0.0, 1.0)  # (K, S)
    dist = np.linalg.norm(a[None] + t[..., None] * d[None] - x[:, None, :], axis=2)
    start = np.concatenate([[0.0], np.cumsum(length)])
    s = np.empty(len(x))
    seg = 0
    for k in range(len(x)):  # forward-only choice of the segment: a short loop over samples
        window = slice(seg, min(seg + lookahead + 1, len(d)))
        seg = window.start + int(np.argmin(dist[k, window]))
        s[k] = start[seg] + t[k, seg] * length[seg]
    s = np.maximum.accumulate(s)
    j = np.clip(np.searchsorted(start, s, side="right") - 1, 0, len(d) - 1)
    return a[j] + ((s - start[j]) / length[j])[:, None] * d[j]
