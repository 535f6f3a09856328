"""The block adjustment does not depend on the simulator (issue 18, item 2).

``geocoder.adjust`` is production code; ``geocoder.simulate`` makes test truth and imports the
adjustment's geometry and data model, never the other way round.  Checked twice: statically,
every import statement anywhere in ``geocoder/adjust/`` (functions and ``TYPE_CHECKING`` blocks
included), and at run time, importing every module of ``geocoder.adjust`` in a fresh
interpreter.  Also: the moved names are the same objects under their old import paths, and the
package's modules stay small.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import geocoder

PACKAGE = Path(geocoder.__file__).parent
ADJUST = PACKAGE / "adjust"

#: Modules of geocoder.adjust allowed over this many lines, each with its reason in its docstring.
MAX_LINES = 500


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path) -> set[str]:
    """Absolute names of every module an import statement in ``path`` names (relative ones resolved)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.add(target)
            # ``from . import x`` may name a submodule
            out.update(f"{target}.{alias.name}" for alias in node.names)
    return out


def _adjust_files() -> list[Path]:
    return sorted(ADJUST.rglob("*.py"))


def test_the_import_parser_sees_cross_package_imports():
    # the simulator imports the adjustment's data model through a relative import: the parser
    # must resolve it, or the test below would pass for the wrong reason
    seen = imported_modules(PACKAGE / "simulate" / "points.py")
    assert "geocoder.adjust.observations" in seen
    assert "geocoder.geodesy" in seen
    assert "geocoder.simulate.satellite" in seen
    assert len(_adjust_files()) >= 20


def test_adjust_imports_nothing_from_simulate_statically():
    offenders = {
        str(p.relative_to(PACKAGE.parent)): sorted(m for m in imported_modules(p) if m.startswith("geocoder.simulate"))
        for p in _adjust_files()
    }
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"geocoder.adjust imports the simulator: {offenders}"


def test_geodesy_is_at_the_bottom():
    seen = imported_modules(PACKAGE / "geodesy.py")
    assert not [m for m in seen if m.startswith("geocoder")], seen


_IMPORT_ALL = """
import importlib, json, pkgutil, sys
import geocoder.adjust
names = sorted(m.name for m in pkgutil.walk_packages(geocoder.adjust.__path__, "geocoder.adjust."))
for name in names:
    importlib.import_module(name)
print(json.dumps({"imported": names, "simulate": sorted(m for m in sys.modules if m.startswith("geocoder.simulate"))}))
"""


def test_importing_every_adjust_module_loads_no_simulator():
    r = subprocess.run([sys.executable, "-c", _IMPORT_ALL], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    expected = {_module_name(p) for p in _adjust_files()} - {"geocoder.adjust"}
    assert set(out["imported"]) == expected
    assert out["simulate"] == [], f"importing geocoder.adjust loaded {out['simulate']}"


def test_moved_names_are_one_object_under_every_path():
    from geocoder import geodesy
    from geocoder.adjust import linescanner_geometry, models, observations, orbit, sensor, solver
    from geocoder.simulate import points, satellite

    assert satellite.LineScanner is linescanner_geometry.LineScanner
    assert satellite.Orbit is orbit.Orbit
    assert satellite.geodetic_to_ecef is geodesy.geodetic_to_ecef
    assert satellite.ecef_to_geodetic is geodesy.ecef_to_geodetic
    assert satellite.WGS84_A == geodesy.WGS84_A and satellite.OMEGA_EARTH == geodesy.OMEGA_EARTH
    for name in ("GroundPoints", "ImageObservations", "point_weight", "edge_weight"):
        assert getattr(points, name) is getattr(observations, name)
    # one protocol and one central-difference Jacobian
    assert solver.SensorModel is models.SensorModel is sensor.SensorModel
    assert models._central_difference is sensor.central_difference
    assert solver.numeric_jacobians is sensor.numeric_jacobians


def test_adjust_modules_are_small_or_say_why():
    too_long = {}
    for p in _adjust_files():
        n = len(p.read_text().splitlines())
        doc = ast.get_docstring(ast.parse(p.read_text())) or ""
        if n > MAX_LINES and "lines because" not in doc:
            too_long[str(p.relative_to(PACKAGE.parent))] = n
    assert not too_long, f"over {MAX_LINES} lines without a reason in the docstring: {too_long}"
