"""pyproject.toml maps the top-level folders to ``agos.*``: every package folder must be listed.

An editable install finds unlisted subpackages anyway (the parent folder is on the path), so a
missing entry only shows in a wheel, where the subpackage is simply absent.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_folder_is_listed_in_pyproject() -> None:
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapped = setuptools["package-dir"]
    assert sorted(mapped) == sorted(setuptools["packages"])
    roots = {folder for name, folder in mapped.items() if name.count(".") == 1}
    on_disk = {str(init.parent.relative_to(ROOT)) for root in roots for init in (ROOT / root).rglob("__init__.py")}
    assert on_disk == set(mapped.values()), f"folders missing from pyproject: {sorted(on_disk - set(mapped.values()))}"
    for name, folder in mapped.items():
        assert name == "agos." + folder.replace("/", "."), name
