"""The answer of ``POST /correspond`` when the ShadowCorr library is not installed.

With the library installed, the clients return its :class:`shadowcorr.result.Result`
(a pydantic model, validated field by field).  A client installed alone
(``pip install ./clients``) has neither the library nor pydantic, and returns a
:class:`ResultView` instead: the same attributes a caller reads (``labels``,
``segments[i].object``, ``objects``, ``metrics``, ``warnings``, ``config``, ...) and the
same ``model_dump`` / ``model_dump_json``, over the JSON the server sent.
"""

from __future__ import annotations

import json
from types import SimpleNamespace
from typing import Any

__all__ = ["ResultView", "parse_result_json"]

_REQUIRED = {"scene": str, "units": str, "method": str, "segments": list, "objects": list}


class ResultView:
    """Read-only attribute access to a result's JSON (see the module docstring)."""

    def __init__(self, data: dict[str, Any]) -> None:
        self._data = data
        self.segments = [SimpleNamespace(**s) for s in data["segments"]]
        self.objects = [SimpleNamespace(**o) for o in data["objects"]]

    def __getattr__(self, name: str) -> Any:
        # Only called for names not set in __init__: the result's other top-level fields.
        data = self.__dict__.get("_data", {})
        if name in data:
            return data[name]
        if name in ("model", "metrics", "config"):
            return None
        if name in ("timings_ms",):
            return {}
        if name == "warnings":
            return []
        raise AttributeError(f"result has no field {name!r}")

    @property
    def labels(self) -> list[int]:
        """Object label of each segment, in segment order."""
        return [s.object for s in self.segments]

    def model_dump(self, mode: str = "python") -> dict[str, Any]:
        return json.loads(json.dumps(self._data))  # a deep copy, like pydantic's dump

    def model_dump_json(self, indent: int | None = None) -> str:
        return json.dumps(self._data, indent=indent)

    def __repr__(self) -> str:
        return f"ResultView(scene={self._data.get('scene')!r}, segments={len(self.segments)}, objects={len(self.objects)})"


def parse_result_json(content: bytes) -> ResultView:
    """Check the shape of a result and wrap it; ``ValueError`` says what is missing."""
    data = json.loads(content)
    if not isinstance(data, dict):
        raise ValueError("expected a JSON object")
    wrong = [k for k, kind in _REQUIRED.items() if not isinstance(data.get(k), kind)]
    if wrong:
        raise ValueError(f"missing or mistyped fields: {', '.join(wrong)}")
    for i, seg in enumerate(data["segments"]):
        if not isinstance(seg, dict) or not isinstance(seg.get("object"), int):
            raise ValueError(f"segments[{i}] has no integer 'object'")
    if not all(isinstance(o, dict) for o in data["objects"]):
        raise ValueError("objects must be JSON objects")
    return ResultView(data)
