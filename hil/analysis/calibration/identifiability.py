"""Which parameters can this dataset separate? Scaled Jacobian, SVD condition numbers, pivoted QR.

Columns are scaled to unit norm (so metres and radians compare), then taken in a priority order
(base and tool first, then the kinematic parameters joint by joint, then effects) and kept only when
their component orthogonal to the columns already kept is larger than `tol` (default 1e-3: a parameter
whose distinct part is smaller is fixed rather than fitted to noise; a QR factorisation with
a prescribed pivot order). A dropped column is a near-combination of kept ones: it is fixed at its
current value and its effect is merged into those parameters, which the report names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class IdentifiabilityReport:
    names: list[str]
    kept: list[str]
    dropped: list[dict] = field(default_factory=list)  # {name, reason, merged_into: [[name, coef], ...]}
    condition_before: float = float("nan")
    condition_after: float = float("nan")
    tol: float = 1e-3

    @property
    def keep_mask(self) -> np.ndarray:
        kept = set(self.kept)
        return np.array([n in kept for n in self.names])

    def to_dict(self) -> dict:
        return {
            "kept": self.kept,
            "dropped": self.dropped,
            "condition_before": self.condition_before,
            "condition_after": self.condition_after,
            "tol": self.tol,
        }

    def summary(self) -> str:
        lines = [
            f"identifiability: {len(self.kept)} of {len(self.names)} parameters kept; condition number of the "
            f"scaled Jacobian {self.condition_before:.3g} -> {self.condition_after:.3g}"
        ]
        for d in self.dropped:
            merged = " ".join(f"{c:+.3g}*{n}" for n, c in d["merged_into"]) or "(no effect on the data)"
            lines.append(f"  dropped {d['name']}: {d['reason']}; its effect ~ {merged}")
        return "\n".join(lines)


def _priority(name: str) -> int:
    if name.startswith("base_"):
        return 0
    if name.startswith(("tool", "probe")):  # a probe's orientation, like its position, before the joints
        return 1
    if "." in name:  # effect coefficients: family_jN.coef
        return 3
    return 2


def condition_number(J: np.ndarray) -> float:
    """2-norm condition number of J with unit-norm columns."""
    if J.shape[1] == 0:
        return 1.0
    R = np.linalg.qr(J, mode="r") if J.shape[0] > J.shape[1] else J  # same singular values, small SVD
    s = np.linalg.svd(R, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def scale_columns(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J with unit-norm columns and the norms (zero columns keep norm 1)."""
    norms = np.linalg.norm(J, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    return J / norms, norms


def analyse(
    J: np.ndarray, names: list[str], tol: float = 1e-3, candidates: np.ndarray | None = None
) -> IdentifiabilityReport:
    """Identifiability of the columns of J (M, P) named `names`; `candidates` masks columns to consider."""
    cand = np.ones(len(names), bool) if candidates is None else np.asarray(candidates, bool)
    idx = [i for i in sorted(range(len(names)), key=lambda i: (_priority(names[i]), i)) if cand[i]]
    Js, _ = scale_columns(J)
    raw_norm = np.linalg.norm(J, axis=0)
    basis = np.empty((len(idx), J.shape[0]))  # orthonormal rows, the first `len(kept_idx)` in use
    kept_idx: list[int] = []
    dropped_idx: list[int] = []
    distinct: dict[int, float] = {}  # part of a dropped column orthogonal to the kept ones
    for i in idx:
        if raw_norm[i] == 0:
            dropped_idx.append(i)
            continue
        r = Js[:, i].copy()
        B = basis[: len(kept_idx)]
        for _ in range(2):  # Gram-Schmidt against every kept column at once, re-orthogonalised once
            r -= (B @ r) @ B
        if np.linalg.norm(r) > tol:
            basis[len(kept_idx)] = r / np.linalg.norm(r)
            kept_idx.append(i)
        else:
            dropped_idx.append(i)
            distinct[i] = float(np.linalg.norm(r))
    kept_idx.sort()
    report = IdentifiabilityReport(
        names=list(names),
        kept=[names[i] for i in kept_idx],
        condition_before=condition_number(Js[:, idx]),
        condition_after=condition_number(Js[:, kept_idx]),
        tol=tol,
    )
    for i in dropped_idx:
        if raw_norm[i] == 0:
            report.dropped.append(
                {"name": names[i], "reason": "the data does not excite it", "merged_into": []}
            )
            continue
        Jk = Js[:, kept_idx]
        coef = np.linalg.solve(Jk.T @ Jk, Jk.T @ Js[:, i]) * raw_norm[i] / raw_norm[kept_idx]
        contrib = np.abs(coef) * np.linalg.norm(J[:, kept_idx], axis=0)
        top = np.argsort(-contrib)[:3]
        merged = [[names[kept_idx[k]], float(coef[k])] for k in top if contrib[k] > 1e-3 * contrib.max()]
        report.dropped.append(
            {
                "name": names[i],
                "reason": f"only {distinct[i]:.1e} of its effect on the data is distinct from parameters kept "
                f"before it (threshold {tol:g}): the data cannot separate them",
                "distinct": distinct[i],
                "merged_into": merged,
            }
        )
    return report
