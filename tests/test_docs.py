"""The README stays a user's page, its links resolve, and the code stays in pieces a newcomer can read."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_README_LINES = 250
MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 120
LONG_REASON = "# long:"  # a function may be longer with this comment on its def line, giving the reason


def _anchor(heading: str) -> str:
    """Returns GitHub's anchor of a markdown heading."""
    a = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return a.replace(" ", "-")


def _anchors(md: Path) -> set[str]:
    return {_anchor(m.group(1)) for m in re.finditer(r"^#+ (.+)$", md.read_text(), re.M)}


def test_readme_is_short_and_its_test_command_is_the_ci_one():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    setup = [b.strip() for b in blocks if b.strip().startswith("python3.11 -m venv .venv")]
    assert len(setup) == 2, "the README has exactly two set-up commands"
    assert "panosfm demo" in setup[0] and "pytest" in setup[1]
    ci = (ROOT / ".ci" / "run").read_text().replace("pip install -q ", "pip install ")  # CI installs quietly
    assert setup[1].replace("python3.11", "$PY") in ci


@pytest.mark.parametrize("md", [README, *sorted((ROOT / "docs").glob("*.md"))], ids=lambda p: p.name)
def test_local_links_resolve(md: Path):
    """Every relative link of the README and docs/ names a file that exists, and an anchor that exists in it."""
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", md.read_text()):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (md.parent / path).resolve() if path else md
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(target)
    assert not broken, f"{md.name}: broken links {broken}"


def test_config_pointers_name_existing_decisions():
    config = (ROOT / "panosfm_graph" / "config.py").read_text()
    anchors = _anchors(ROOT / "docs" / "decisions.md")
    pointed = re.findall(r"decisions\.md#([\w\-]+)", config)
    assert pointed, "config.py points into docs/decisions.md"
    assert sorted(set(pointed) - anchors) == []


def _sources() -> list[Path]:
    return sorted((ROOT / "panosfm_graph").rglob("*.py")) + sorted((ROOT / "factors").rglob("*.py"))


def test_modules_and_functions_stay_short():
    """No module of the library over 700 lines, no function over 120 (or a one-line reason on its def line)."""
    long_modules, long_functions = [], []
    for path in _sources():
        src = path.read_text()
        lines = src.splitlines()
        if len(lines) > MAX_MODULE_LINES:
            long_modules.append(f"{path.relative_to(ROOT)}: {len(lines)}")
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES and LONG_REASON not in lines[node.lineno - 1]:
                    long_functions.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {n}")
    assert not long_modules and not long_functions, (long_modules, long_functions)
