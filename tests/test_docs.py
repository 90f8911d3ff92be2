"""The documentation site (issue 45): it builds with warnings as errors, every public name has a docstring
and a place in the API reference, and the README's links into ``docs/`` land on a file and a heading."""

import dataclasses
import importlib
import inspect
import re
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
# Each package whose __all__ the API reference covers, and its page (docs/api/<page>.md).
PAGES = {
    "torchrl_dalir": "torchrl_dalir",
    "torchrl_dalir.envs": "envs",
    "torchrl_dalir.experts": "experts",
    "torchrl_dalir.data": "data",
    "torchrl_dalir.modules": "modules",
    "torchrl_dalir.objectives": "objectives",
    "torchrl_dalir.training": "training",
    "torchrl_dalir.reranking": "reranking",
    "torchrl_dalir.evaluation": "evaluation",
    "torchrl_dalir.checkpoints": "checkpoints",
    "torchrl_dalir.pipeline": "pipeline",
}


def _public(package: str) -> list[tuple[str, object]]:
    module = importlib.import_module(package)
    return [(name, getattr(module, name)) for name in module.__all__]


def _is_constant(obj) -> bool:
    return not (inspect.isclass(obj) or inspect.isroutine(obj) or inspect.ismodule(obj))


def _own_docstring(obj) -> str:
    """``obj``'s own docstring: not a base class's, nor the signature a dataclass without one gets."""
    doc = vars(obj).get("__doc__") if inspect.isclass(obj) else obj.__doc__
    doc = inspect.cleandoc(doc or "")
    if inspect.isclass(obj) and dataclasses.is_dataclass(obj) and doc.startswith(f"{obj.__name__}("):
        return ""
    return doc


def _inventory(path: Path) -> set[str]:
    """The Python objects a Sphinx ``objects.inv`` lists (version 2: 4 header lines, then zlib)."""
    body = zlib.decompress(path.read_bytes().split(b"\n", 4)[4]).decode()
    names = set()
    for line in body.splitlines():
        match = re.match(r"(\S+)\s+py:\w+\s+-?\d+\s", line)
        if match:
            names.add(match.group(1))
    return names


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site, built as the README says (warnings are errors), into a temporary folder."""
    for package in ("sphinx", "myst_parser", "furo"):
        pytest.importorskip(package)  # pip install -e ".[docs]"
    out = tmp_path_factory.mktemp("html")
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-q", "-j", "1", str(DOCS), str(out)]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, f"the docs build failed:\n{done.stdout[-4000:]}\n{done.stderr[-8000:]}"
    return out


def test_the_site_builds_with_the_api_reference_guides_and_results(site):
    page = (site / "api" / "reranking.html").read_text()
    assert 'id="torchrl_dalir.reranking.RerankingActor"' in page
    assert "candidates per decision (the paper: 32)" in page  # an argument of its Args section
    assert "from_checkpoints" in page  # its methods
    for built in ("index", "guides/index", "guides/dalir", "guides/main_job", "results/README", "measurements"):
        assert (site / f"{built}.html").exists(), built
    # a re-exported constant carries the doc comment of the module that defines it, not tuple's docstring
    assert "Built-in immutable sequence" not in page


@pytest.mark.parametrize("package", PAGES)
def test_every_public_name_has_a_docstring(package):
    missing = [name for name, obj in _public(package) if not _is_constant(obj) and not _own_docstring(obj)]
    assert not missing, f"{package}: public names without a docstring of their own: {missing}"


@pytest.mark.parametrize("package", PAGES)
def test_every_public_constant_has_a_doc_comment(package):
    pytest.importorskip("sphinx")
    sys.path.insert(0, str(DOCS / "_ext"))
    try:
        from dalir_autodoc import data_doc
    finally:
        sys.path.remove(str(DOCS / "_ext"))
    missing = [name for name, obj in _public(package) if _is_constant(obj) and not data_doc(package, name)]
    assert not missing, f"{package}: public constants without a '#:' doc comment where they are defined: {missing}"


def test_every_public_name_is_in_the_api_reference(site):
    documented = _inventory(site / "objects.inv")
    problems = []
    for package, page_name in PAGES.items():
        page = (site / "api" / f"{page_name}.html").read_text()
        for name, obj in _public(package):
            # documented under this package, or (a re-export) under the package it comes from
            homes = [full for full in documented if full == f"{package}.{name}" or full.endswith(f".{name}")]
            here = f"{package}.{name}" in homes or any(
                getattr(sys.modules.get(full.rpartition(".")[0]), name, None) is obj for full in homes
            )
            if not here:
                problems.append(f"{package}.{name}: documented on no page (add it to docs/api/{page_name}.md)")
            elif name not in page:
                problems.append(f"{package}.{name}: not named on docs/api/{page_name}.md")
    assert not problems, "\n".join(problems)


def _slug(heading: str) -> str:
    """The anchor GitHub (and MyST, with myst_heading_anchors) gives a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)  # not the '# comments' of code blocks
    return {_slug(line.lstrip("#")) for line in text.splitlines() if re.match(r"#{1,6} ", line)}


@pytest.mark.parametrize("source", ["README.md", "docs/usage.md", "docs/results/README.md"])
def test_relative_links_land_on_a_file_and_a_heading(source):
    path = ROOT / source
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", path.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        file, _, anchor = target.partition("#")
        linked = (path.parent / file).resolve()
        if not linked.exists():
            broken.append(target)
        elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
            broken.append(target)
    assert not broken, f"{source}: links to a missing file or heading: {broken}"
