"""The documentation cannot go stale: the site builds strictly, what it names exists, the README stays short.

docs/ is a mkdocs-material site (mkdocs.yml, `strict: true`, with validation that turns a page left out of the
nav, a link to a missing page and a link to a missing anchor into failures); README.md is the front page. Here:
the strict build passes, and fails on a copy with a page deleted or a link broken; every repository path the
README and the pages write in backticks, code blocks or links exists (and every dotted module name); the
Layout trees name only files that exist and every Python package; every setting, HTTP route and command is
documented; the README is at most 150 lines.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS_DIR = ROOT / "docs"
README = ROOT / "README.md"
README_MAX_LINES = 150
PAGES = sorted(DOCS_DIR.glob("*.md"))
DOC_FILES = [README, *PAGES]

# a word whose first folder is one of these is a repository path even without a file suffix (`tests/faults`)
TOP_DIRS = frozenset({"services", "api", "workers", "cli", "bench", "scripts", "tests", "docs", ".ci"})
PATH_SUFFIXES = (".py", ".sh", ".md", ".toml", ".yml", ".yaml")
# paths the pages name on purpose that are not files of the repository: data under data_dir, the shared scans
# and spec next to the checkout, build and run outputs
NOT_REPO_PATHS = (
    "../shared/",
    "data_dir/",
    "jobs/",
    "demo-out/",
    "tests/artifacts/",
    "api/static/vendor/",
    ".venv/",
    "node_modules/",
)
PACKAGE_ROOTS = ("services", "api", "workers", "cli")
CORE = ROOT / "services" / "core"

FENCED = re.compile(r"^```[^\n]*\n(.*?)^```", re.M | re.S)
CODE_SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")
LINK = re.compile(r"\]\(([^)\s]+)\)")
DOTTED = re.compile(r"^(?:services|api|workers|cli)(?:\.[A-Za-z_]\w*)+$")
BRACES = re.compile(r"\{([^{}]*)\}")


# --- the strict build ---------------------------------------------------------------------------------------


def _build(project: Path, site: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # mkdocs-material's banner about MkDocs 2.0
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=project,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )


def _nav_pages(config: dict) -> list[str]:
    pages = []
    for entry in config["nav"]:
        pages.extend(entry.values() if isinstance(entry, dict) else [entry])
    return pages


def test_strict_build_passes_with_every_page_in_the_nav(tmp_path: Path) -> None:
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    assert config["strict"] is True and config["docs_dir"] == "docs" and config["theme"]["name"] == "material"
    assert sorted(_nav_pages(config)) == sorted(p.name for p in PAGES), "every page of docs/ is in the nav, once"
    built = _build(ROOT, tmp_path / "site")
    assert built.returncode == 0, built.stdout + built.stderr
    for page in PAGES:
        html = tmp_path / "site" / ("index.html" if page.stem == "index" else f"{page.stem}/index.html")
        assert html.is_file(), f"{page.name} was not built"


def _delete_a_nav_page(docs: Path) -> None:
    (docs / "design.md").unlink()


def _link_a_missing_page(docs: Path) -> None:
    with (docs / "index.md").open("a") as f:
        f.write("\nSee [the old guide](guide.md).\n")


def _link_a_missing_anchor(docs: Path) -> None:
    with (docs / "operations.md").open("a") as f:
        f.write("\nSee [the routes](api.md#no-such-section).\n")


@pytest.mark.parametrize("breakage", [_delete_a_nav_page, _link_a_missing_page, _link_a_missing_anchor])
def test_strict_build_fails_on_a_broken_copy(tmp_path: Path, breakage) -> None:
    project = tmp_path / "project"
    shutil.copytree(DOCS_DIR, project / "docs")
    shutil.copy(ROOT / "mkdocs.yml", project / "mkdocs.yml")
    breakage(project / "docs")
    built = _build(project, tmp_path / "site")
    assert built.returncode != 0, f"{breakage.__name__}: the strict build passed\n{built.stderr}"
    assert "WARNING" in built.stderr, built.stderr


# --- paths and module names -----------------------------------------------------------------------------------


def _words(text: str) -> list[str]:
    """Return the words of code spans and of indented code blocks (commands), outside fenced blocks."""
    words: list[str] = []
    prose = FENCED.sub("", text)
    for span in CODE_SPAN.findall(prose):
        words += span.split()
    for line in prose.splitlines():
        if line.startswith("    ") and not line.lstrip().startswith(("-", "|", "*")):
            words += line.split()
    return words


def _expand(word: str) -> list[str]:
    """Expand one brace group with commas (`stages/{prepare,send}.py`); other braces stay."""
    for m in BRACES.finditer(word):
        if "," in m.group(1):
            return [w for alt in m.group(1).split(",") for w in _expand(word[: m.start()] + alt + word[m.end() :])]
    return [word]


def _repo_path(word: str, tree: bool = False) -> str | None:
    """Return the repository path a word names, or None when it names none.

    In a fenced block (a tree, a diagram: `core/` there is relative to the lines above it) only a word that
    starts at a top-level folder is a repository path.
    """
    w = word.split("::")[0].lstrip("([\"'").rstrip(")],;:.\"'")
    if tree and w.split("/")[0] not in TOP_DIRS:
        return None
    if "/" not in w or "://" in w or "=" in w or "..." in w or w.startswith(("/", "$", "@", "-", "~")):
        return None
    if w.startswith(NOT_REPO_PATHS):
        return None
    if w.endswith(PATH_SUFFIXES) or w.endswith("/") or w.split("/")[0] in TOP_DIRS:
        return w
    return None


def _exists(path: str, base: Path) -> bool:
    """A path exists; a placeholder (`<resource>`, `{id}`) needs its folder, a glob one match."""
    if "<" in path or "{" in path:
        folder = re.split(r"[<{]", path)[0].rsplit("/", 1)[0]
        return (base / folder).is_dir()
    if "*" in path:
        return any(base.glob(path))
    return (base / path).exists()


def _module_exists(dotted: str) -> bool:
    """`services.core.x` is a module or package; `services.core.x.name` also needs `name` defined in it."""
    parts = dotted.split(".")
    for n in (len(parts), len(parts) - 1):
        base = ROOT.joinpath(*parts[:n])
        source = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        if source.is_file():
            if n == len(parts):
                return True
            defined = rf"^\s*(?:def|class|async def)\s+{parts[-1]}\b|^{parts[-1]}\s*[:=]"
            return re.search(defined, source.read_text(), re.M) is not None
    return False


def missing_references(text: str, base: Path) -> list[str]:
    """Return the repository paths, links and module names in `text` that do not exist (links from `base`)."""
    missing = []
    tree_words = [(word, True) for block in FENCED.findall(text) for word in block.split()]
    for word, tree in [*tree_words, *((word, False) for word in _words(text))]:
        path = _repo_path(word, tree)
        if path is not None:
            missing += [p for p in _expand(path) if not _exists(p, ROOT)]
        dotted = word.strip("`()[],;.").replace(":", ".")
        if DOTTED.match(dotted) and not _module_exists(dotted):
            missing.append(dotted)
    for target in LINK.findall(FENCED.sub("", text)):
        if target.startswith(("http://", "https://", "mailto:", "#")):
            continue
        if not (base / target.split("#")[0]).exists():
            missing.append(target)
    return missing


@pytest.mark.parametrize("doc", DOC_FILES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_path_and_module_named_exists(doc: Path) -> None:
    missing = missing_references(doc.read_text(), doc.parent)
    assert not missing, f"{doc.relative_to(ROOT)} names what does not exist: {missing}"


def test_the_reference_check_finds_what_is_missing() -> None:
    text = (
        "The loop is `workers/main.py` and `workers/stages/{prepare,gone}.py`; see [the API](api.md), "
        "[old](docs/old.md), `services.core.pipeline.reconstruct`, `services.core.nowhere` and "
        "`services.core.pipeline.no_such_function`.\n\n    bash scripts/missing.sh\n\n"
        "```text\ntests/gone/\n```\nData in `data_dir/sessions/<id>/raw`, routes in `api/routes/<resource>.py`.\n"
    )
    assert sorted(missing_references(text, DOCS_DIR)) == [
        "docs/old.md",
        "scripts/missing.sh",
        "services.core.nowhere",
        "services.core.pipeline.no_such_function",
        "tests/gone/",
        "workers/stages/gone.py",
    ]


# --- the Layout trees -----------------------------------------------------------------------------------------

NAME = re.compile(r"^(?:[\w.-]*\{[\w.,-]+\}[\w.-]*|[\w.-]+)(?:/[\w.-]+)*/?$")


def _is_name(token: str) -> bool:
    return bool(NAME.match(token)) and ("." in token or token.endswith("/") or token == "Dockerfile")


def layout_entries(text: str) -> list[Path]:
    """Return the paths the first code block under `## Layout` names.

    Each line is `<indent><name> <name> ...  <description>` (two spaces or more before the description); a
    line with one folder name opens that folder for the lines indented under it; a line that does not start
    with names continues a description.
    """
    section = re.search(r"^## Layout\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert section, "no ## Layout section"
    block = FENCED.search(section.group(1))
    assert block, "no code block under ## Layout"
    entries: list[Path] = []
    stack: list[tuple[int, Path]] = []
    for line in block.group(1).splitlines():
        tokens = re.split(r"\s{2,}", line.strip())[0].split(" ")
        if not line.strip() or not all(_is_name(t) for t in tokens):
            continue
        indent = len(line) - len(line.lstrip(" "))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        base = stack[-1][1] if stack else ROOT
        paths = [base / name for token in tokens for name in _expand(token)]
        entries += paths
        if len(tokens) == 1 and tokens[0].endswith("/"):
            stack.append((indent, paths[0]))
    return entries


def _packages() -> set[Path]:
    return {
        init.parent
        for root in PACKAGE_ROOTS
        for init in (ROOT / root).rglob("__init__.py")
        if "__pycache__" not in init.parts
    }


@pytest.mark.parametrize("doc", [README, DOCS_DIR / "contributing.md"], ids=["README.md", "contributing.md"])
def test_layout_names_only_what_exists(doc: Path) -> None:
    entries = layout_entries(doc.read_text())
    assert len(entries) >= 15, f"the layout parser found only {len(entries)} entries in {doc.name}"
    missing = [p.relative_to(ROOT).as_posix() for p in entries if not p.exists()]
    assert not missing, f"{doc.name}'s Layout names what does not exist: {missing}"


def test_full_layout_names_every_package() -> None:
    named = set(layout_entries((DOCS_DIR / "contributing.md").read_text()))
    unnamed = sorted(p.relative_to(ROOT).as_posix() for p in _packages() - named)
    assert not unnamed, f"docs/contributing.md's Layout does not name these packages: {unnamed}"


def test_readme_layout_names_every_top_level_folder_and_core_step() -> None:
    named = {p.relative_to(ROOT).as_posix().rstrip("/") for p in layout_entries(README.read_text())}
    folders = {d for d in TOP_DIRS - {".ci"} if (ROOT / d).is_dir()}
    packages = {p.relative_to(ROOT).as_posix() for p in _packages() if p.parent in (ROOT / "services", CORE)}
    unnamed = sorted((folders | packages) - named)
    assert not unnamed, f"README.md's Layout does not name: {unnamed}"


# --- what must be documented ----------------------------------------------------------------------------------


def test_every_setting_is_in_the_operators_guide() -> None:
    from services.settings import Settings, WorkerSettings

    text = (DOCS_DIR / "operations.md").read_text()
    env = {name: "REDIS_URL" if name == "redis_url" else f"VEINMOSAIC_{name.upper()}" for name in Settings.model_fields}
    missing = [var for var in env.values() if f"`{var}`" not in text]
    missing += [name for name in WorkerSettings.model_fields if f"`{name}`" not in text]
    assert not missing, f"docs/operations.md does not document: {missing}"


def test_every_route_is_in_the_api_guide() -> None:
    from api.app import create_app

    text = (DOCS_DIR / "api.md").read_text()
    routes = [f"{method.upper()} {path}" for path, ops in create_app().openapi()["paths"].items() for method in ops]
    assert len(routes) > 20
    missing = [route for route in routes if route not in text]
    assert not missing, f"docs/api.md does not list: {missing}"


def test_every_command_is_in_the_command_table() -> None:
    from cli.main import build_parser

    text = (DOCS_DIR / "command-line.md").read_text()
    commands = next(a.choices for a in build_parser()._actions if a.choices and isinstance(a.choices, dict))
    missing = [name for name in commands if f"| `veinmosaic {name}" not in text]
    assert not missing, f"docs/command-line.md's table does not list: {missing}"


def test_readme_is_a_front_page() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines (at most {README_MAX_LINES})"
    text = "\n".join(lines)
    assert "    bash scripts/demo.sh\n" in text and "    bash scripts/test.sh\n" in text, "the two commands"
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text(), "CI runs the README's test command"
    linked = set(re.findall(r"\]\(docs/([\w-]+\.md)\)", text))
    assert linked >= {p.name for p in PAGES} - {"index.md"}, "the README links every page"
