"""The flange face as the operator sees it, for the tool fit's prompts: the hole circle, holes 1-7 numbered and
the place the SMR goes next marked, so "seat SMR 1 in flange hole 3" comes with where hole 3 is.

Seen facing the flange (its z axis towards the viewer): flange +x to the right, +y up. SVG text, drawn from
the cell config's hole layout (the same nominal points the fit is judged against).
"""

from __future__ import annotations

import numpy as np

VIEW_PX = 240  # the drawing's width and height
HOLE_PX = 9  # a hole's radius in the drawing


def flange_drawing_svg(points_m: dict[str, np.ndarray], asked: str, face_point_m: tuple[float, float]) -> str:
    """The flange with `asked` marked ("hole1".."hole7", or "face": the resting point); `points_m` the nominal
    SMR centres by location (flange frame, m)."""
    holes = {k: v for k, v in points_m.items() if k.startswith("hole")}
    reach = max(float(np.hypot(*p[:2])) for p in holes.values()) * 1.35
    scale = (VIEW_PX / 2 - 6) / reach

    def xy(x_m: float, y_m: float) -> tuple[float, float]:
        return VIEW_PX / 2 + x_m * scale, VIEW_PX / 2 - y_m * scale  # +y up on the screen

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {VIEW_PX} {VIEW_PX}" '
        f'role="img" aria-label="the flange face, {asked.replace("hole", "hole ")} marked">',
        f'<circle cx="{VIEW_PX / 2}" cy="{VIEW_PX / 2}" r="{reach * scale:.1f}" fill="#eef1f4" stroke="#57606a"/>',
    ]
    for name, p in sorted(holes.items()):
        cx, cy = xy(float(p[0]), float(p[1]))
        marked = name == asked
        fill, ring = (
            ("#d4a72c", ' stroke="#9a6700" stroke-width="3"') if marked else ("#ffffff", ' stroke="#57606a"')
        )
        parts.append(
            f'<circle class="{"asked" if marked else "hole"}" data-location="{name}" cx="{cx:.1f}" cy="{cy:.1f}" '
            f'r="{HOLE_PX}" fill="{fill}"{ring}/>'
        )
        parts.append(
            f'<text x="{cx:.1f}" y="{cy + 4:.1f}" font-size="11" text-anchor="middle">{name.removeprefix("hole")}</text>'
        )
    if asked == "face":
        cx, cy = xy(*face_point_m)
        parts.append(
            f'<circle class="asked" data-location="face" cx="{cx:.1f}" cy="{cy:.1f}" r="{HOLE_PX + 3}" '
            'fill="#d4a72c" stroke="#9a6700" stroke-width="3"/>'
        )
    parts.append('<text x="4" y="12" font-size="10">facing the flange, +x &#8594;</text>')
    parts.append("</svg>")
    return "".join(parts)
