"""The documentation runs: its examples are extracted from the Markdown and executed, never copied.

What runs, against the sample scene, each page in a temporary directory of its own holding
``examples/`` (the repository's) and a copy of ``out/sample_bundle`` (which ``scripts/setup.sh``
makes; converted here when it is missing):

* every ```` ```python ```` block of ``README.md`` and of ``docs/**/*.md``: a page's blocks run in
  order in one interpreter and one namespace, as a reader would type them (all pages share one
  process, each page with a fresh namespace and working directory);
* every shell block (```` ```bash ````, ``sh``, ``shell``) of the README's "Quick start" section,
  in order, each with ``bash -e -o pipefail``, with the venv's commands first on ``PATH``.

An HTML comment on the line just before a block's opening fence tells the test what to do:

* ``<!-- docs-test: skip (reason) -->``: the block is not run (installs, docker, data you must bring
  yourself); the reason is required;
* ``<!-- docs-test: server -->``: the block starts the service; it is not run, and the test starts
  a real server (``tests/harness.py`` ``ServerProcess``) in its place.  Every block of a page with
  this marker, and every block that calls ``127.0.0.1:8000``, runs with that server's address in
  place of ``127.0.0.1:8000`` and in ``SHADOWCORR_SERVER``.

Any other marker is an error, so a typo cannot silently skip a block.  Shell blocks outside the
README's quick start are not run.  Also checked here: the README stays a front door (at most 250
lines) and no page says how the project was developed.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.harness import ServerProcess
from tests.paths import REPO, SAMPLE_DIR

README = REPO / "README.md"
DOCS = REPO / "docs"
SERVICE_ADDRESS = "127.0.0.1:8000"
MARKER = re.compile(r"^\s*<!--\s*docs-test:\s*(?P<kind>[\w-]+)\s*(?:\((?P<reason>[^)]*)\))?\s*-->\s*$")
FENCE = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*(?P<lang>[\w+-]*)")
SHELL = {"bash", "sh", "shell"}


@dataclass
class Block:
    path: Path
    line: int  # 1-based line of the block's first code line
    lang: str
    code: str
    marker: str | None
    reason: str | None
    section: str  # the "## " heading the block sits under

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(REPO)}:{self.line}"


def parse_blocks(path: Path) -> list[Block]:
    """Every fenced block of a Markdown file, with the marker on the line before its fence."""
    lines = path.read_text().splitlines()
    blocks: list[Block] = []
    section = ""
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("## "):
            section = line[3:].strip()
        m = FENCE.match(line)
        if not m:
            i += 1
            continue
        indent, fence = m.group("indent"), m.group("fence")
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        code = textwrap.dedent("\n".join(lines[i + 1:j])) if indent else "\n".join(lines[i + 1:j])
        prev = lines[i - 1] if i > 0 else ""
        mm = MARKER.match(prev)
        blocks.append(Block(path, i + 2, m.group("lang").lower(), code + "\n",
                            mm.group("kind") if mm else None, mm.group("reason") if mm else None, section))
        i = j + 1
    return blocks


def doc_pages() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def runnable(block: Block) -> bool:
    if block.marker is not None:
        return False
    if block.lang == "python":
        return True
    return block.path == README and block.lang in SHELL and block.section.lower().startswith("quick start")


def needs_server(blocks: list[Block]) -> bool:
    return any(b.marker == "server" for b in blocks) or any(SERVICE_ADDRESS in b.code for b in blocks if runnable(b))


PAGES = {p: parse_blocks(p) for p in doc_pages()}
PYTHON_PAGES = [p for p, blocks in PAGES.items() if any(runnable(b) and b.lang == "python" for b in blocks)]
QUICK_START_SHELL = [b for b in PAGES[README] if runnable(b) and b.lang in SHELL]


def test_markers_are_known_and_examples_are_found() -> None:
    bad = [f"{b.where}: docs-test: {b.marker} ({b.reason})" for blocks in PAGES.values() for b in blocks
           if b.marker not in (None, "skip", "server") or (b.marker == "skip" and not (b.reason or "").strip())]
    assert not bad, "unknown marker, or skip without a reason (see tests/test_docs.py):\n" + "\n".join(bad)
    stray = [str(p.relative_to(REPO)) for p in doc_pages() if "docs-test" in p.read_text()
             and not any(b.marker for b in PAGES[p]) and p.name != "development.md"]
    assert not stray, f"a docs-test marker that is not on the line before a fence: {stray}"
    assert len(QUICK_START_SHELL) >= 2, "the README's quick start has no shell blocks to run"
    assert sum(runnable(b) and b.lang == "python" for blocks in PAGES.values() for b in blocks) >= 10


def test_readme_is_a_front_door() -> None:
    assert len(README.read_text().splitlines()) <= 250


DEVELOPMENT_WORDS = re.compile(r"\bsessions?\b|previous host|done[- ]when|the cost issue|previous release|"
                               r"release before|\bissue #?\d+", re.IGNORECASE)


def prose(text: str) -> str:
    """``text`` without fenced blocks and inline code (words there may mean something else)."""
    text = re.sub(r"^(\s*)(`{3,}|~{3,}).*?^\1\2\s*$", "", text, flags=re.MULTILINE | re.DOTALL)
    return re.sub(r"`[^`\n]*`", "", text)


def test_no_page_says_how_the_project_was_developed() -> None:
    found = []
    for path in [*doc_pages(), REPO / "CHANGELOG.md"]:
        for n, line in enumerate(prose(path.read_text()).splitlines(), 1):
            if DEVELOPMENT_WORDS.search(line):
                found.append(f"{path.relative_to(REPO)}: {line.strip()}")
    assert not found, "\n".join(found)


# ------------------------------------------------------------------ running the examples
RUNNER = r'''
import contextlib, io, json, os, sys, time, traceback, urllib.request

pages, server, out_path = json.load(open(sys.argv[1])), os.environ.get("SHADOWCORR_SERVER"), sys.argv[2]
results = {}


def wait_for_server(deadline_s=300.0):
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        try:
            with urllib.request.urlopen(server + "/health", timeout=5) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise TimeoutError("the test's server did not get ready")


for page in pages:
    os.chdir(page["workspace"])
    output = io.StringIO()
    namespace = {"__name__": "__main__"}
    try:
        if page["server"]:
            wait_for_server()
        with contextlib.redirect_stdout(output):
            for block in page["blocks"]:
                exec(compile("\n" * (block["line"] - 1) + block["code"], block["path"], "exec"), namespace)
        results[page["page"]] = {"ok": True, "output": output.getvalue()}
    except BaseException:
        results[page["page"]] = {"ok": False, "output": output.getvalue(), "error": traceback.format_exc()}
with open(out_path, "w") as f:
    json.dump(results, f)
'''


@pytest.fixture(scope="module")
def sample_bundle(tmp_path_factory) -> Path:
    """``out/sample_bundle`` as ``scripts/setup.sh`` makes it (converted here when missing)."""
    made = REPO / "out" / "sample_bundle"
    if (made / "manifest.json").exists():
        return made
    from shadowcorr.convert import convert_ue

    return Path(convert_ue(SAMPLE_DIR, 2001, [0, 2, 4, 6], tmp_path_factory.mktemp("bundle") / "sample_bundle"))


def workspace(root: Path, page: Path, bundle: Path) -> Path:
    ws = root / re.sub(r"[^\w.-]", "_", str(page.relative_to(REPO)))
    (ws / "out").mkdir(parents=True)
    (ws / "examples").symlink_to(REPO / "examples", target_is_directory=True)
    shutil.copytree(bundle, ws / "out" / "sample_bundle")
    return ws


def with_server(code: str, server: ServerProcess | None) -> str:
    return code.replace(SERVICE_ADDRESS, server.url.removeprefix("http://")) if server else code


def run_env(server: ServerProcess | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWCORR_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTHONPATH", None)  # the installed packages, as a reader has them
    if server:
        env["SHADOWCORR_SERVER"] = server.url
    return env


@pytest.fixture(scope="module")
def docs_server():
    if not any(needs_server(PAGES[p]) for p in PYTHON_PAGES) and not needs_server(PAGES[README]):
        yield None
        return
    server = ServerProcess(["--workers", "1"], env={"SHADOWCORR_LOG_LEVEL": "warning"})
    server.launch()  # warms up while the pages without a server run
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="module")
def workspaces(tmp_path_factory, sample_bundle) -> dict[Path, Path]:
    root = tmp_path_factory.mktemp("docs")
    return {page: workspace(root, page, sample_bundle) for page in [*PYTHON_PAGES, *([README] if README not in PYTHON_PAGES else [])]}


@pytest.fixture(scope="module")
def python_results(tmp_path_factory, workspaces, docs_server) -> dict[str, dict]:
    """Run every page's Python blocks in one interpreter (pages needing the server last)."""
    pages = []
    for page in sorted(PYTHON_PAGES, key=lambda p: needs_server(PAGES[p])):
        server = docs_server if needs_server(PAGES[page]) else None
        blocks = [{"line": b.line, "path": str(b.path.relative_to(REPO)), "code": with_server(b.code, server)}
                  for b in PAGES[page] if runnable(b) and b.lang == "python"]
        pages.append({"page": str(page.relative_to(REPO)), "workspace": str(workspaces[page]),
                      "server": server is not None, "blocks": blocks})
    tmp = tmp_path_factory.mktemp("runner")
    (tmp / "pages.json").write_text(json.dumps(pages))
    (tmp / "runner.py").write_text(RUNNER)
    proc = subprocess.run([sys.executable, str(tmp / "runner.py"), str(tmp / "pages.json"), str(tmp / "results.json")],
                          env=run_env(docs_server), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"the example runner failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return json.loads((tmp / "results.json").read_text())


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_python_examples_run(page: Path, python_results) -> None:
    got = python_results[str(page.relative_to(REPO))]
    assert got["ok"], f"{got.get('error')}\noutput:\n{got['output'][-2000:]}"


def test_readme_quick_start_runs(workspaces, docs_server) -> None:
    server = docs_server if needs_server(PAGES[README]) else None
    if server:
        server.wait_ready()
    for block in QUICK_START_SHELL:
        proc = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", with_server(block.code, server)],
                              cwd=workspaces[README], env=run_env(server), capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, f"{block.where} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    assert (workspaces[README] / "out" / "result.json").exists()
