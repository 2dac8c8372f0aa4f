"""The measurement dataset contract: one CSV row per measured robot pose, rows in measurement order.

Required: ``q1_rad .. q6_rad`` (joints the robot reported) and ``x_mm, y_mm, z_mm`` (SMR centre in the
tracker frame). Optional: ``t_s`` (seconds since the campaign started), ``temperature_c`` (the arm's
temperature: the tracker's object probe where it read every point, else the robot's joint sensors where they did,
else the air's; thermal effects are driven by it), ``air_temperature_c`` (the tracker's weather station;
campaigns recorded before it was exported lack it), ``robot_temperature_c`` (the robot's own reading), ``smr``
(nest id, integer; default 1), ``payload_kg``, ``pose`` (which rows share one robot pose), ``rx_deg, ry_deg,
rz_deg`` (a 6-DoF probe's orientation in the tracker frame, extrinsic x-y-z: R = Rz(rz) Ry(ry) Rx(rx)), ``cycle``
(an ISO 9283 campaign's cycle, hil.analysis.standards.iso9283), ``sweep`` (a joint sweep's label, hil.analysis.standards.joint_axes), and any
further column whose name ends in its unit.
"""

from __future__ import annotations

import hashlib
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

POSITION_COLUMNS: tuple[str, ...] = ("x_mm", "y_mm", "z_mm")
OPTIONAL_COLUMNS: tuple[str, ...] = ("t_s", "temperature_c", "smr", "payload_kg", "pose", "cycle", "sweep")
ORIENTATION_COLUMNS: tuple[str, ...] = ("rx_deg", "ry_deg", "rz_deg")
# What the robot was told to reach, in the same frame and units (ISO 9283 campaigns, path campaigns).
CMD_POSITION_COLUMNS: tuple[str, ...] = ("x_cmd_mm", "y_cmd_mm", "z_cmd_mm")
CMD_ORIENTATION_COLUMNS: tuple[str, ...] = ("rx_cmd_deg", "ry_cmd_deg", "rz_cmd_deg")
# Conventions of the three orientation angles, as scipy's Euler sequences (lower case = extrinsic axes).
# Inside hil the angles always follow the default; another convention is converted when the data is read.
ORIENTATION_CONVENTIONS: dict[str, str] = {
    "xyz-extrinsic": "xyz",  # about the fixed tracker axes x, then y, then z: R = Rz(rz) Ry(ry) Rx(rx)
    "xyz-intrinsic": "XYZ",  # about the moving axes x, then y', then z'': R = Rx(rx) Ry(ry) Rz(rz)
}
DEFAULT_ORIENTATION_CONVENTION = "xyz-extrinsic"
# Rows whose joints all agree within this (rad) were measured at one robot pose (several SMRs, or revisits).
SAME_POSE_RAD = 2e-4
UNIT_SUFFIX = re.compile(r"_(mm|m|um|rad|deg|s|ms|c|k|kg|n|nm|hpa|pa|pct|mps|bool|id|count)$", re.IGNORECASE)


def joint_columns(n_joints: int = 6) -> list[str]:
    return [f"q{i + 1}_rad" for i in range(n_joints)]


class DatasetError(ValueError):
    """A dataset that breaks the contract; the message says what to fix."""


def validate_dataset(
    df: pd.DataFrame, n_joints: int = 6, source: str = "dataset", require_positions: bool = True
) -> pd.DataFrame:
    """Check a frame against the contract and return it with clean dtypes (raises DatasetError).

    `require_positions=False` accepts a joints-only file (targets to predict). Columns labelled in
    degrees (`q1_deg`) or metres (`x_m`) are converted; exact duplicate rows are dropped, counted once
    and reported (warning and `attrs["duplicate_rows"]`); `attrs["row_numbers"]` keeps each row's data
    row number in the file (from 1).
    """
    df = _convert_units(df, n_joints)
    required = joint_columns(n_joints) + (list(POSITION_COLUMNS) if require_positions else [])
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DatasetError(
            f"{source}: missing column(s) {', '.join(missing)}; a dataset needs {', '.join(required)} "
            f"(found: {', '.join(map(str, df.columns))})"
        )
    if len(df) == 0:
        raise DatasetError(f"{source}: no rows")
    out = df.copy()
    present = [c for c in ORIENTATION_COLUMNS if c in df.columns]
    if present and len(present) < 3:
        raise DatasetError(
            f"{source}: orientation needs all of {', '.join(ORIENTATION_COLUMNS)} (found only "
            f"{', '.join(present)}); give the probe's three angles or none"
        )
    numeric = required + [c for c in ("t_s", "temperature_c", "payload_kg", *present) if c in df.columns]
    for col in numeric:
        values = pd.to_numeric(out[col], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(values.to_numpy(float)))
        if bad.size:
            rows = ", ".join(str(r + 1) for r in bad[:5])
            raise DatasetError(
                f"{source}: column '{col}' has missing or non-numeric values in data row(s) {rows}"
                f"{' ...' if bad.size > 5 else ''} (row 1 = first line after the header)"
            )
        out[col] = values.astype(float)
    if "smr" in out.columns:
        smr = pd.to_numeric(out["smr"], errors="coerce")
        if smr.isna().any() or np.any(smr != np.round(smr)):
            row = int(np.flatnonzero(smr.isna() | (smr != np.round(smr)))[0]) + 1
            raise DatasetError(
                f"{source}: column 'smr' must hold integer nest ids (bad value in data row {row})"
            )
        out["smr"] = smr.astype(int)
    if "pose" in out.columns:
        blank = (out["pose"].isna() | (out["pose"].astype(str).str.strip() == "")).to_numpy()
        if blank.any():
            rows = ", ".join(str(r + 1) for r in np.flatnonzero(blank)[:5])
            raise DatasetError(
                f"{source}: column 'pose' is blank in data row(s) {rows}{' ...' if blank.sum() > 5 else ''} "
                "(row 1 = first line after the header); give every row its pose id, or drop the column to "
                "group rows by their joints"
            )
    q = out[joint_columns(n_joints)].to_numpy()
    if np.any(np.abs(q) > 4 * np.pi):
        row = int(np.flatnonzero(np.any(np.abs(q) > 4 * np.pi, axis=1))[0]) + 1
        raise DatasetError(
            f"{source}: joint angles beyond 4*pi in data row {row} look like degrees; give radians in "
            "q1_rad.. or name the columns q1_deg.."
        )
    if require_positions:
        _check_positions_are_mm(out, source)
    if "t_s" in out.columns and np.any(np.diff(out["t_s"].to_numpy()) < 0):
        row = int(np.flatnonzero(np.diff(out["t_s"].to_numpy()) < 0)[0]) + 2
        raise DatasetError(
            f"{source}: t_s goes backwards at data row {row}; rows must be in measurement order"
        )
    unknown = [
        c
        for c in out.columns
        if c not in required and c not in OPTIONAL_COLUMNS and not UNIT_SUFFIX.search(str(c))
    ]
    if unknown:
        warnings.warn(
            f"{source}: column(s) {', '.join(map(str, unknown))} carry no unit suffix (e.g. '_mm'); ignored",
            stacklevel=2,
        )
    return drop_duplicate_rows(out, source)


def _convert_units(df: pd.DataFrame, n_joints: int) -> pd.DataFrame:
    """`qi_deg` -> `qi_rad`, `x_m` -> `x_mm` where the contract's column is absent."""
    renames = {}
    for i in range(1, n_joints + 1):
        if f"q{i}_rad" not in df.columns and f"q{i}_deg" in df.columns:
            renames[f"q{i}_deg"] = (f"q{i}_rad", np.pi / 180.0)
    for ax in "xyz":
        if f"{ax}_mm" not in df.columns and f"{ax}_m" in df.columns:
            renames[f"{ax}_m"] = (f"{ax}_mm", 1000.0)
    if not renames:
        return df
    out = df.copy()
    for old, (new, factor) in renames.items():
        out[new] = pd.to_numeric(out[old], errors="coerce") * factor
    return out.drop(columns=list(renames))


def _check_positions_are_mm(df: pd.DataFrame, source: str) -> None:
    """A robot campaign spans hundreds of millimetres: positions within a few units are metres."""
    p = float_columns(df, POSITION_COLUMNS)
    if len(p) >= 5 and np.max(np.abs(p)) < 20.0 and np.max(np.ptp(p, axis=0)) < 10.0:
        raise DatasetError(
            f"{source}: x_mm, y_mm, z_mm span only {np.max(np.ptp(p, axis=0)):.3g} and stay within "
            f"{np.max(np.abs(p)):.3g}: they look like metres; multiply by 1000 or name the columns x_m, y_m, z_m"
        )


def drop_duplicate_rows(df: pd.DataFrame, source: str = "dataset") -> pd.DataFrame:
    """Exact copies of a row (same joints, positions, SMR and orientation) counted once, reported by data
    row. Several SMRs read at one pose differ in `smr` and position, so they are all kept."""
    rows = data_rows(df)
    subset = [c for c in df.columns if re.fullmatch(r"q\d+_rad", str(c))]
    subset += [c for c in (*POSITION_COLUMNS, "smr", *ORIENTATION_COLUMNS) if c in df.columns]
    dup = df.duplicated(subset=subset, keep="first").to_numpy()
    out = df
    if dup.any():
        listed = ", ".join(str(r) for r in rows[dup][:8]) + (" ..." if dup.sum() > 8 else "")
        warnings.warn(
            f"{source}: {int(dup.sum())} duplicated row(s) (data rows {listed}) repeat an earlier row; "
            "each is counted once (check the export)",
            stacklevel=3,
        )
        out = df.loc[~dup].reset_index(drop=True)
    dropped = [*df.attrs.get("duplicate_rows", []), *rows[dup].tolist()]
    out.attrs = {**df.attrs, "row_numbers": RowNumbers(rows[~dup]), "duplicate_rows": dropped}
    return out


class RowNumbers:
    """Read-only data row numbers kept in a frame's attrs: pandas deep-copies attrs on every operation, and
    a list of 12 000 ints made each column access of a big campaign cost milliseconds; this is shared."""

    __slots__ = ("values",)

    def __init__(self, values: np.ndarray) -> None:
        self.values = np.array(values, int)
        self.values.flags.writeable = False

    def __deepcopy__(self, memo: dict) -> RowNumbers:
        return self

    def __len__(self) -> int:
        return len(self.values)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RowNumbers) and np.array_equal(self.values, other.values)

    __hash__ = None  # type: ignore[assignment]


def data_rows(df: pd.DataFrame) -> np.ndarray:
    """Data row number in the source file (from 1) of each row of a validated frame."""
    rows = df.attrs.get("row_numbers")
    if rows is not None and len(rows) == len(df):
        return np.array(rows.values if isinstance(rows, RowNumbers) else rows, int)
    return np.arange(1, len(df) + 1)


def load_dataset(path: str | Path, n_joints: int = 6, require_positions: bool = True) -> pd.DataFrame:
    """Read and validate a dataset CSV."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"dataset file not found: {path}")
    try:
        df = _read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not a readable CSV ({exc}); export it as CSV text") from exc
    out = validate_dataset(df, n_joints, source=str(path), require_positions=require_positions)
    out.attrs.update(
        source=str(path), sha256=hashlib.sha256(path.read_bytes()).hexdigest(), rows_in_file=len(df)
    )
    return out


def _read_csv(path: Path) -> pd.DataFrame:
    """CSV with ',' or (spreadsheet export) ';' / tab separators; ';' files may use decimal commas."""
    with open(path, encoding="utf-8-sig", newline="") as f:
        header, first = f.readline(), f.readline()
    counts = {sep: header.count(sep) for sep in (",", ";", "\t")}
    sep = max(counts, key=lambda k: counts[k]) if max(counts.values()) > 0 else ","
    decimal = "," if sep != "," and re.search(r"\d,\d", first) else "."
    if sep == "," and first.count(",") > header.count(","):
        raise DatasetError(
            f"{path}: data rows have more fields than the header ({first.count(',') + 1} vs "
            f"{header.count(',') + 1}): decimal commas in a comma-separated file? export with ';' "
            "separators or decimal points"
        )
    return pd.read_csv(path, sep=sep, decimal=decimal, encoding="utf-8-sig")


def write_dataset(df: pd.DataFrame, path: str | Path) -> None:
    """Validate and write a dataset CSV (full float precision)."""
    validate_dataset(df, source=str(path)).to_csv(path, index=False, float_format="%.10g")


def make_dataset(
    q: np.ndarray,
    p_tracker_m: np.ndarray,
    t_s: np.ndarray | None = None,
    temperature_c: np.ndarray | None = None,
    smr: np.ndarray | int | None = None,
    R_tracker_probe: np.ndarray | None = None,
) -> pd.DataFrame:
    """Build a contract frame from arrays in SI units (probe orientations (N, 3, 3) become rx/ry/rz_deg)."""
    q = np.atleast_2d(q)
    data: dict[str, np.ndarray] = {c: q[:, i] for i, c in enumerate(joint_columns(q.shape[1]))}
    p_mm = np.atleast_2d(p_tracker_m) * 1000.0
    for i, c in enumerate(POSITION_COLUMNS):
        data[c] = p_mm[:, i]
    if t_s is not None:
        data["t_s"] = np.asarray(t_s, float)
    if temperature_c is not None:
        data["temperature_c"] = np.asarray(temperature_c, float)
    if smr is not None:
        data["smr"] = np.broadcast_to(np.asarray(smr, int), (q.shape[0],)).copy()
    if R_tracker_probe is not None:
        data.update(orientation_columns(R_tracker_probe))
    return pd.DataFrame(data)


def float_columns(df: pd.DataFrame, columns: Sequence[str]) -> np.ndarray:
    """The columns (N, len(columns)) as floats: what df[list(columns)].to_numpy(float) gives, a column at a
    time (a fit reads the joints hundreds of times, and selecting them as a frame first took 4x as long);
    a missing column raises pandas' own KeyError naming every missing one."""
    out = np.empty((len(df), len(columns)))
    try:
        for j, column in enumerate(columns):
            out[:, j] = df[column].to_numpy(float)
    except KeyError:
        df[list(columns)]  # raises the KeyError that names every missing column
        raise
    return out


def joints_rad(df: pd.DataFrame, n_joints: int = 6) -> np.ndarray:
    return float_columns(df, joint_columns(n_joints))


def points_m(df: pd.DataFrame) -> np.ndarray:
    return float_columns(df, POSITION_COLUMNS) / 1000.0


def commanded_points_m(df: pd.DataFrame) -> np.ndarray:
    """The commanded positions (x_cmd_mm, y_cmd_mm, z_cmd_mm) in metres; a cell that is not a number reads as NaN."""
    return df[list(CMD_POSITION_COLUMNS)].apply(pd.to_numeric, errors="coerce").to_numpy(float) / 1000.0


def angles_rad(df: pd.DataFrame, columns: tuple[str, ...] = ORIENTATION_COLUMNS) -> np.ndarray:
    """Angle columns given in degrees (the probe's rx/ry/rz_deg by default), in radians."""
    return np.deg2rad(float_columns(df, columns))


def smr_ids(df: pd.DataFrame) -> np.ndarray:
    return df["smr"].to_numpy(int) if "smr" in df.columns else np.ones(len(df), int)


def has_orientation(df: pd.DataFrame) -> bool:
    """Whether the rows carry a 6-DoF probe's orientation (rx_deg, ry_deg, rz_deg)."""
    return all(c in df.columns for c in ORIENTATION_COLUMNS)


def check_orientation_convention(name: str) -> str:
    """The convention's scipy sequence; ValueError naming the known ones for anything else."""
    if name not in ORIENTATION_CONVENTIONS:
        raise ValueError(
            f"unknown orientation convention '{name}'; choose {' or '.join(ORIENTATION_CONVENTIONS)}"
        )
    return ORIENTATION_CONVENTIONS[name]


def orientations(df: pd.DataFrame, convention: str = DEFAULT_ORIENTATION_CONVENTION) -> np.ndarray | None:
    """Probe orientations R_tracker_probe (N, 3, 3) from rx_deg, ry_deg, rz_deg in `convention` (the
    default one inside hil), or None when the frame has no orientation columns."""
    from scipy.spatial.transform import Rotation

    seq = check_orientation_convention(convention)
    if not has_orientation(df):
        return None
    angles = angles_rad(df)
    return Rotation.from_euler(seq, angles).as_matrix()


def orientation_columns(
    R_tracker_probe: np.ndarray, convention: str = DEFAULT_ORIENTATION_CONVENTION
) -> dict[str, np.ndarray]:
    """rx_deg, ry_deg, rz_deg of rotations (N, 3, 3), in `convention` (the default one inside hil)."""
    from scipy.spatial.transform import Rotation

    seq = check_orientation_convention(convention)
    angles = np.rad2deg(Rotation.from_matrix(np.asarray(R_tracker_probe, float)).as_euler(seq))
    return dict(zip(ORIENTATION_COLUMNS, angles.T, strict=True))


def convert_orientation_convention(df: pd.DataFrame, convention: str) -> pd.DataFrame:
    """The frame with rx_deg, ry_deg, rz_deg re-expressed from `convention` in the default one (the
    convention hil uses inside); unchanged without orientation columns or in the default convention."""
    R = orientations(df, convention)
    if R is None or convention == DEFAULT_ORIENTATION_CONVENTION:
        return df
    out = df.copy()
    for col, values in orientation_columns(R).items():
        out[col] = values
    return out


def pose_ids(df: pd.DataFrame) -> np.ndarray:
    """Which robot pose each row was measured at (N,) ints from 0, in order of first appearance.

    A `pose` column says it; otherwise rows whose joints all agree within SAME_POSE_RAD are one pose
    (several SMRs read while the robot stood still, or the same joints visited again). Rows of one pose
    share the robot's systematic error, so cross-validation must keep them in one fold.
    """
    if "pose" in df.columns:
        label = np.unique(df["pose"].astype(str).to_numpy(), return_inverse=True)[1].ravel()
    else:
        q = float_columns(df, [c for c in df.columns if re.fullmatch(r"q\d+_rad", str(c))])
        if len(q) == 0:
            return np.zeros(0, int)
        label = _near_groups(q, SAME_POSE_RAD)
    _, first = np.unique(label, return_index=True)
    rank = np.empty(len(first), int)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[label]


def _near_groups(q: np.ndarray, tol: float) -> np.ndarray:
    """Connected components (N,) of the rows of `q` linked when all coordinates agree within `tol`.

    Rows are first collapsed to the grid cells of size `tol` they fall in (rows of one cell all agree
    within `tol`), then only cells next to each other are compared row by row: memory and time grow with
    the rows, not with the pairs of rows (thousands of rows at one pose, a drift log, stay cheap).
    """
    from scipy.spatial import cKDTree

    cells, cell_of = np.unique(np.floor(q / tol).astype(np.int64), axis=0, return_inverse=True)
    cell_of = cell_of.ravel()
    n_cells = len(cells)
    order = np.argsort(cell_of, kind="stable")
    bounds = np.searchsorted(cell_of[order], np.arange(n_cells + 1))
    # Cells whose indices differ by at most 1 in every joint may hold rows within tol of each other.
    near = cKDTree(cells.astype(float)).query_pairs(1.0, p=np.inf, output_type="ndarray")
    reach = np.nextafter(tol, np.inf)  # query's bound is strict; rows exactly tol apart are one pose
    parent = np.arange(n_cells)

    def root(c: int) -> int:
        while parent[c] != c:
            parent[c] = parent[parent[c]]
            c = int(parent[c])
        return c

    trees: dict[int, cKDTree] = {}
    for a, b in near:
        ra, rb = root(int(a)), root(int(b))
        if ra == rb:
            continue  # already one pose through other cells
        rows_a, rows_b = (order[bounds[c] : bounds[c + 1]] for c in (a, b))
        if len(rows_a) > len(rows_b):
            a, b, rows_a, rows_b = b, a, rows_b, rows_a
        tree = trees.get(int(b))
        if tree is None:
            tree = trees[int(b)] = cKDTree(q[rows_b])
        if np.isfinite(tree.query(q[rows_a], k=1, p=np.inf, distance_upper_bound=reach)[0]).any():
            parent[ra] = rb
    roots = np.array([root(c) for c in range(n_cells)], int)
    return np.unique(roots, return_inverse=True)[1].ravel()[cell_of]


def repeated_orientation_counts(df: pd.DataFrame, pose: np.ndarray) -> np.ndarray:
    """How many rows of each row's pose carry exactly its rx/ry/rz_deg (N,), ones without orientation.

    A single-probe export writes the pose's one orientation reading on every SMR row of that pose: the
    copies are one measurement, not several.
    """
    if not has_orientation(df) or len(df) == 0:
        return np.ones(len(df), int)
    key = pd.DataFrame({"pose": np.asarray(pose)}).join(
        df[list(ORIENTATION_COLUMNS)].reset_index(drop=True).astype(float)
    )
    return key.groupby(list(key.columns), sort=False)["pose"].transform("size").to_numpy(int)
