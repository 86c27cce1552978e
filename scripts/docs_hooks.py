"""MkDocs hooks (mkdocs.yml ``hooks:``): parts of pages generated from the code, so they cannot drift.

``<!-- generated: service-settings -->`` in a page becomes the table of the service's settings,
read from ``shadowcorr_service.settings.ServiceSettings``: environment variable, ``shadowcorr
serve`` flag, default and meaning (each field's description).

``<!-- generated: stages-reference -->`` becomes one section per stage module, in the order the
stages run, holding a mkdocstrings directive for every public name of ``shadowcorr.stages`` that
the module defines (the stages are exported lazily, which static analysis cannot list).
"""

from __future__ import annotations

from typing import Any

SETTINGS_MARKER = "<!-- generated: service-settings -->"
STAGES_MARKER = "<!-- generated: stages-reference -->"
_MiB = 1024 * 1024


def _default_text(name: str, value: Any) -> str:
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return str(value).lower()
    if name.endswith("_bytes") and isinstance(value, int) and value >= _MiB and value % _MiB == 0:
        mib = value // _MiB
        return f"{value} ({mib // 1024} GiB)" if mib % 1024 == 0 else f"{value} ({mib} MiB)"
    return str(value)


def service_settings_table() -> str:
    """Markdown table of every ``ServiceSettings`` field."""
    from shadowcorr_service.settings import ServiceSettings

    rows = ["| environment variable | `shadowcorr serve` flag | default | meaning |", "|---|---|---|---|"]
    for name, field in ServiceSettings.model_fields.items():
        flag = {"auth_token": "`--auth-token-file` (a file holding it)", "model_path": "`--model`"}.get(
            name, f"`--{name.replace('_', '-')}`")
        meaning = (field.description or "").replace("|", "\\|")
        rows.append(f"| `SHADOWCORR_{name.upper()}` | {flag} | {_default_text(name, field.default)} | {meaning} |")
    return "\n".join(rows)


def stages_reference() -> str:
    """Markdown: a heading per stage module (its docstring's first line) and a ``:::`` directive per public name."""
    import importlib

    import shadowcorr.stages as stages

    by_module: dict[str, list[str]] = {}
    for name in stages.__all__:
        module = getattr(getattr(stages, name), "__module__", None)
        if module is None or not module.startswith("shadowcorr.stages."):  # constants: find the defining module
            module = next(m for m in (f"shadowcorr.stages.{f}" for f in _stage_modules())
                          if name in vars(importlib.import_module(m)))
        by_module.setdefault(module, []).append(name)
    parts = []
    for module in sorted(by_module):
        doc = (importlib.import_module(module).__doc__ or module).strip().splitlines()[0].rstrip(".")
        parts.append(f"## {doc}\n")
        parts += [f"::: shadowcorr.stages.{name}\n" for name in sorted(by_module[module])]
    return "\n".join(parts)


def _stage_modules() -> list[str]:
    from pathlib import Path

    import shadowcorr.stages as stages

    return sorted(p.stem for p in Path(stages.__file__).parent.glob("_[0-9]*.py"))


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    if SETTINGS_MARKER in markdown:
        markdown = markdown.replace(SETTINGS_MARKER, service_settings_table())
    if STAGES_MARKER in markdown:
        markdown = markdown.replace(STAGES_MARKER, stages_reference())
    return markdown
