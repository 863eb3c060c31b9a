"""The README's Python examples run as written."""

from __future__ import annotations

import pathlib
import re
import textwrap

import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_examples():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
@pytest.mark.slow
def test_readme_example_runs(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # examples that write (run directories) write here
    exec(compile(textwrap.dedent(BLOCKS[index]), f"README.md python block {index}", "exec"), {})  # blocks in lists are indented


def _layout_paths() -> list[str]:
    """The paths in the first column of the README's Layout tables."""
    section = README.read_text().split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^\| `([^`]+)` \|", section, flags=re.M)


def test_layout_section_matches_the_tree():
    """Every folder and module the README's Layout lists exists, and every package folder
    and module of the tree is listed."""
    root = README.parent
    listed = _layout_paths()
    missing = [p for p in listed if not (root / p).exists()]
    assert not missing, f"README Layout lists paths that do not exist: {missing}"
    folders = {f"{d.relative_to(root).as_posix()}/" for top in ("mjx_multiarm", "models", "train", "eval")
               for d in [root / top, *(root / top).rglob("*")] if d.is_dir() and (d / "__init__.py").exists()}
    folders |= {"benchmarks/", "notebooks/", "tests/", "mjx_multiarm/assets/"}
    modules = {p.relative_to(root).as_posix() for top in ("mjx_multiarm", "models", "train", "eval")
               for p in (root / top).rglob("*.py") if p.name != "__init__.py"}
    modules.add("benchmarks/common.py")
    unlisted = sorted((folders | modules) - set(listed))
    assert not unlisted, f"README Layout does not list: {unlisted}"


def test_package_docstrings_list_their_modules():
    """Each package's docstring names every module in it (``:mod:`.name```), so that
    ``help(package)`` shows the layout; ``__main__`` modules are the command lines."""
    import ast

    root = README.parent
    unlisted = []
    for init in [p for top in ("mjx_multiarm", "train", "eval") for p in (root / top).rglob("__init__.py")]:
        if init.parent.name == "mjx_multiarm":
            continue  # the top package re-exports the public API instead
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        unlisted += [f"{init.parent.name}.{p.stem}" for p in init.parent.glob("*.py")
                     if p.stem not in ("__init__", "__main__") and f":mod:`.{p.stem}`" not in doc]
    assert not unlisted, f"package docstrings do not list: {unlisted}"
