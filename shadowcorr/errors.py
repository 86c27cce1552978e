"""Error types for everything that reads user input (bundles, uploads, converters).

A bad bundle is reported *once*, with every problem found, so that a user fixing a
manifest does not have to resubmit it once per mistake.  Each problem carries a
``loc`` that points into the manifest the way a user reads it::

    views[2:cam_left].depth.file   view index 2, named "cam_left", field depth.file
    manifest                       the manifest as a whole (JSON syntax, size, ...)
    archive                        the .zip / .tar container
    files["a/b.png"]               an uploaded part / archive member

The view name is in the loc whenever it is known, because users think in view names,
while the index keeps the loc unambiguous when names are missing or duplicated.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

__all__ = [
    "Problem",
    "BundleError",
    "view_loc",
    "format_loc",
    "problems_from_validation_error",
    "SceneLimitError",
]


class Problem(BaseModel):
    """One thing wrong with an input: where (``loc``) and what (``msg``).

    A frozen pydantic model so the HTTP service can return ``[p.model_dump() ...]``
    directly in its ``problems`` list.
    """

    model_config = ConfigDict(frozen=True)

    loc: str
    msg: str

    def __str__(self) -> str:
        return f"{self.loc}: {self.msg}" if self.loc else self.msg


class BundleError(ValueError):
    """A bundle (or an uploaded part of one) could not be loaded.

    ``problems`` lists every problem found; ``str(err)`` names all of them, so a log
    line or a CLI message is complete on its own.  Subclasses ``ValueError`` so code
    that only knows "bad input" can still catch it.
    """

    def __init__(self, problems: Problem | Sequence[Problem] | str, loc: str = "") -> None:
        if isinstance(problems, str):
            items = [Problem(loc=loc, msg=problems)]
        elif isinstance(problems, Problem):
            items = [problems]
        else:
            items = list(problems)
        if not items:  # an error without a reason helps nobody; keep the invariant
            items = [Problem(loc=loc, msg="invalid bundle")]
        self.problems: list[Problem] = items
        super().__init__(self._render())

    def _render(self) -> str:
        n = len(self.problems)
        head = "1 problem" if n == 1 else f"{n} problems"
        return f"{head} in bundle: " + "; ".join(str(p) for p in self.problems)

    def __str__(self) -> str:
        return self._render()

    def to_dicts(self) -> list[dict[str, str]]:
        """JSON-ready problem list (``[{"loc": ..., "msg": ...}]``)."""
        return [p.model_dump() for p in self.problems]


class DepthRangeError(ValueError):
    """Nearly every segment of a scene has no valid depth point (wrong ``units``, or ``max_depth`` too small).

    Such a scene would come out as "one object per segment" with nothing to match, which
    looks like a result but is not one; callers (the CLI, the HTTP service) report it as
    bad input.
    """


class SceneLimitError(ValueError):
    """A scene exceeds one of the configured limits (``max_segments``, ``max_voxels``,
    ``max_stage_seconds``).

    Raised right after the measured quantity is known and before the heavy stages that
    scale with it.  ``limit`` names the configuration field, ``value`` is what the scene
    has and ``maximum`` what the field allows; ``what`` says what was measured when the
    field's name does not (e.g. which stage ran too long).
    """

    def __init__(self, limit: str, value: float, maximum: float, what: str | None = None) -> None:
        self.limit, self.value, self.maximum, self.what = limit, value, maximum, what
        def text(x: float) -> str:
            return f"{x:.3g}" if isinstance(x, float) else str(x)

        measured = f"{what}: {text(value)}" if what else f"it has {text(value)}"
        super().__init__(f"the scene exceeds {limit} = {text(maximum)}: {measured}")


def _join(prefix: str, loc: str) -> str:
    if not prefix:
        return loc
    if not loc:
        return prefix
    return prefix + ("" if loc.startswith("[") else ".") + loc


def view_loc(index: int, name: str | None = None) -> str:
    """Loc of a view: ``views[2:cam0]`` when the name is known, else ``views[2]``."""
    return f"views[{index}:{name}]" if name else f"views[{index}]"


def format_loc(parts: Iterable[Any], view_names: Sequence[str | None] = ()) -> str:
    """Render a pydantic-style loc tuple as ``views[2:cam0].depth.file``.

    Integers become ``[i]`` suffixes; an index right after ``views`` also gets the view
    name from ``view_names`` when there is one.
    """
    out = ""
    prev: Any = None
    for part in parts:
        if isinstance(part, int):
            name = view_names[part] if prev == "views" and 0 <= part < len(view_names) else None
            out += f"[{part}:{name}]" if name else f"[{part}]"
        else:
            out = f"{out}.{part}" if out else str(part)
        prev = part
    return out


def _raw_view_names(data: Any) -> list[str | None]:
    """View names from an unvalidated manifest, ``None`` where a view has no usable name."""
    views = data.get("views") if isinstance(data, dict) else None
    if not isinstance(views, list):
        return []
    names: list[str | None] = []
    for v in views:
        name = v.get("name") if isinstance(v, dict) else None
        names.append(name if isinstance(name, str) and name else None)
    return names


def problems_from_validation_error(err: ValidationError, data: Any = None, prefix: str = "") -> list[Problem]:
    """Turn a pydantic ``ValidationError`` of the ``Manifest`` into ``Problem`` s.

    ``data`` is the raw manifest dict that failed validation; it supplies the view
    names for the locs.  Model-level errors (empty loc) are reported at ``prefix`` or
    ``manifest``.  pydantic's ``"Value error, "`` prefix is dropped: it is noise to users.
    """
    names = _raw_view_names(data)
    problems: list[Problem] = []
    for e in err.errors(include_url=False):
        # pydantic marks "the key of this dict entry was bad" with a '[key]' loc part;
        # the entry's own key just before it already says where, so drop the marker.
        parts = [p for p in e.get("loc", ()) if p != "[key]"]
        loc = format_loc(parts, names)
        loc = _join(prefix, loc) if prefix else (loc or "manifest")
        msg = str(e.get("msg", "invalid value"))
        for noise in ("Value error, ", "Assertion failed, "):
            if msg.startswith(noise):
                msg = msg[len(noise):]
        problems.append(Problem(loc=loc, msg=msg))
    return problems
