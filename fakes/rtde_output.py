"""The data packages of one RTDE output recipe, packed from the controller's values of the moment.

ur-rtde's receive interface asks for 58 variables every controller cycle, and a third of them the fake does not
model (zeros) or holds fixed (the supply voltages, the accelerometer). `OutputPacker` lays those into the
package's flat value list once, when the recipe is set up, and reads every other variable fresh for every
package: the bytes are those `Recipe.pack` makes of all the variables' current values, for a third less work
per package (an idle e-Series cell packs 1 000 a second for two clients).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from fakes import rtde_wire as w

Getter = Callable[[], Any]  # the current value of one output variable (a scalar, or a sequence of its width)


class OutputPacker:
    """One output recipe's package: fixed variables packed in once, the others read at every `package()`."""

    def __init__(self, recipe: w.Recipe, getters: Sequence[Getter], fixed: Sequence[bool]):
        """`getters` in the recipe's order; `fixed[i]` says the i-th variable's value can never change."""
        template: list[Any] = []
        self._scalars: list[tuple[int, Getter]] = []  # (position in the flat values, getter)
        self._vectors: list[tuple[int, int, Getter]] = []  # (first, past-the-last position, getter)
        for getter, type_name, is_fixed in zip(getters, recipe.types, fixed, strict=True):
            width, start = w.TYPE_WIDTH[type_name], len(template)
            if is_fixed:
                value = getter()
                template.extend([value] if width == 1 else value)
            elif width == 1:
                template.append(None)
                self._scalars.append((start, getter))
            else:
                template.extend([None] * width)
                self._vectors.append((start, start + width, getter))
        self._template = template
        self._struct = recipe.packer
        self._recipe_id = bytes([recipe.recipe_id])

    def package(self) -> bytes:
        """The payload of a data package now: the recipe id, then every variable's value packed."""
        flat = self._template.copy()
        for index, getter in self._scalars:
            flat[index] = getter()
        for start, stop, getter in self._vectors:
            flat[start:stop] = getter()
        return self._recipe_id + self._struct.pack(*flat)
