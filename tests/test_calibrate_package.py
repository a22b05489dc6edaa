"""stages.calibrate as a package: modules import downward only, stay small, and the
public names vet_cli, tests and docs use are importable from the package."""

from __future__ import annotations

import ast
from pathlib import Path

import stages.calibrate as c

PACKAGE = Path(c.__file__).parent

#: The floors of the package, bottom first: a module may import only those before it.
LAYERS = (
    "gray_code",
    "geometry",
    "sensor_models",
    "frame_clock",
    "meas_flat",
    "calfile",
    "frames",
    "acquire",
    "cell_leakage",
    "parts",
    "recorded_parts",
    "recorded",
    "folder_out",
    "emulated",
    "emulated_folder",
    "live",
    "run",
    "selftest",
)


def _package_imports(path: Path) -> set[str]:
    """Modules of this package that ``path`` imports (relative or absolute, any depth)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1:
                if node.module:
                    out.add(node.module.split(".")[0])
                else:
                    out.update(a.name for a in node.names)
            elif node.level == 0 and (node.module or "").startswith("stages.calibrate."):
                out.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("stages.calibrate."):
                    out.add(a.name.split(".")[2])
    return out


def test_every_module_has_a_floor_and_imports_only_below_it():
    modules = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__", "__main__"}
    assert modules == set(LAYERS)
    for i, name in enumerate(LAYERS):
        below = set(LAYERS[:i])
        imported = _package_imports(PACKAGE / f"{name}.py")
        assert imported <= below, f"{name} imports {sorted(imported - below)} (not below it)"


def test_no_module_over_600_lines():
    sizes = {p.name: len(p.read_text().splitlines()) for p in PACKAGE.glob("*.py")}
    assert max(sizes.values()) <= 600, sizes


def test_public_names_used_elsewhere_are_exported():
    used = (
        "AcquisitionSettings Calibration apply_calibration calibrate_from_folder calibrate_rig "
        "calibrate_sim calibration_changes calibration_overrides dark_model decode_gray "
        "example_homography fit_homography gray_bit_counts gray_code_patterns "
        "homography_error_px parse_homography read_calibration read_frame run_calibration "
        "selftest write_calibration"
    ).split()
    assert set(used) <= set(c.__all__)
    assert all(callable(getattr(c, n)) for n in used)
