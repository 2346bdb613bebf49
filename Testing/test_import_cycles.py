"""The import-cycle finder (Testing/import_cycles.py) on small packages written here."""

from pathlib import Path

from import_cycles import import_cycles, import_edges


def write_package(root: Path, files: dict) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "pkg"


def test_a_deferred_import_inside_a_function_still_closes_a_cycle(tmp_path):
    package = write_package(tmp_path, {"pkg/__init__.py": "", "pkg/a.py": "from . import b\n",
                                       "pkg/b.py": "def f():\n    from .a import x\n    return x\n",
                                       "pkg/c.py": "from .a import y\n"})
    [(modules, edges)] = import_cycles(package)
    assert modules == ["pkg.a", "pkg.b"]
    deferred = [e for e in edges if e.importer == "pkg.b"]
    assert [(e.name, e.line, e.in_function) for e in deferred] == [("x", 2, True)]


def test_absolute_parent_relative_and_subpackage_init_edges(tmp_path):
    package = write_package(tmp_path, {"pkg/__init__.py": "from .a import q\n", "pkg/a.py": "q = 1\n",
                                       "pkg/c.py": "import pkg.d\n", "pkg/d.py": "from pkg.sub.e import y\n",
                                       "pkg/sub/__init__.py": "", "pkg/sub/e.py": "from ..c import z\n",
                                       "pkg/sub/f.py": "from .. import a\n"})
    [(modules, _)] = import_cycles(package)
    assert modules == ["pkg.c", "pkg.d", "pkg.sub.e"]        # pkg.sub is run on the way but leads nowhere
    pairs = {(e.importer, e.imported) for e in import_edges(package)}
    assert {("pkg.d", "pkg.sub"), ("pkg.sub.f", "pkg.a"), ("pkg", "pkg.a")} <= pairs


def test_a_tree_without_cycles_reports_none(tmp_path):
    package = write_package(tmp_path, {"pkg/__init__.py": "", "pkg/base.py": "import json\n",
                                       "pkg/mid.py": "from .base import json\n",
                                       "pkg/top.py": "from . import base, mid\nimport pkg.mid\n"})
    assert import_cycles(package) == []
    assert len(import_edges(package)) == 4
