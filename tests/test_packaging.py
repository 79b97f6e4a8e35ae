"""pyproject.toml maps the top-level folders to ``agos.*`` (and agos/ to ``agos`` itself): every package
folder must be listed.

An editable install finds unlisted subpackages anyway (the parent folder is on the path), so a
missing entry only shows in a wheel, where the subpackage is simply absent. A folder of data files
only (the human console's page) is listed as a package of its own with its package-data, never as a
``sub/*`` pattern of its parent: setuptools warns about the latter at every install.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_folder_is_listed_in_pyproject() -> None:
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapped = setuptools["package-dir"]
    assert sorted(mapped) == sorted(setuptools["packages"])
    assert mapped["agos"] == "agos"  # the package itself: the library's modules (docs/LIBRARY.md)
    assert not [p for p in (ROOT / "agos").iterdir() if p.is_dir() and p.name != "__pycache__"], \
        "agos/ holds modules only: a subpackage is a top-level folder of its own"
    roots = {folder for name, folder in mapped.items() if name.count(".") == 1}
    on_disk = {str(init.parent.relative_to(ROOT)) for root in roots for init in (ROOT / root).rglob("__init__.py")}
    on_disk.add("agos")
    data = setuptools.get("package-data", {})
    data_only = {folder for name, folder in mapped.items() if name in data and not (ROOT / folder / "__init__.py").exists()}
    assert on_disk == set(mapped.values()) - data_only, \
        f"folders missing from pyproject: {sorted(on_disk - set(mapped.values()))}"
    for name, patterns in data.items():  # data in a subfolder is that folder's own package's
        assert name in mapped and not [p for p in patterns if "/" in p], (name, patterns)
        assert any(any((ROOT / mapped[name]).glob(p)) for p in patterns), (name, patterns)
    for name, folder in mapped.items():
        assert name == "agos" if folder == "agos" else name == "agos." + folder.replace("/", "."), name
