"""The architecture as a contract: layers, one owner per outside library, no circles,
and no heavy library loaded on a path that does not use it (docs/architecture.md)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = "from importlinter.cli import lint_imports; raise SystemExit(lint_imports(no_cache=True))"


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    """Run the import contracts of ``root``/pyproject.toml on the package under ``root``."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(
        [sys.executable, "-c", LINT], cwd=root, env=env, capture_output=True, text=True, timeout=120
    )


def test_import_contracts_hold() -> None:
    result = _lint(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("core/units.py", "from ..app import fit as _fit  # noqa", "imports flow one way"),
        ("identify/design.py", "import h5py as _h5py  # noqa", "h5py only in formats"),
        ("render/law.py", "import serial as _serial  # noqa", "pyserial only in hw.link"),
    ],
)
def test_a_violation_breaks_its_contract(
    tmp_path: Path, module: str, line: str, contract: str
) -> None:
    shutil.copytree(ROOT / "tissuecli", tmp_path / "tissuecli")
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    target = tmp_path / "tissuecli" / module
    target.write_text(target.read_text() + "\n" + line + "\n")
    result = _lint(tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    broken = [ln for ln in result.stdout.splitlines() if ln.endswith("BROKEN")]
    assert any(contract in ln for ln in broken) or contract in result.stdout.split("BROKEN")[0]


def test_no_import_circles() -> None:
    graph = grimp.build_graph("tissuecli", cache_dir=None)
    circles = [
        (importer, imported)
        for importer in graph.modules
        for imported in graph.find_modules_directly_imported_by(importer)
        if imported.startswith("tissuecli") and graph.chain_exists(imported, importer)
    ]
    assert not circles, circles


@pytest.mark.parametrize(
    ("code", "absent"),
    [
        # a fit without a report or a sampler loads neither matplotlib, emcee nor scipy
        ("import tissuecli.app.fit, tissuecli.cli", ("matplotlib", "emcee", "scipy")),
        ("import tissuecli.app.play", ("matplotlib", "emcee", "scipy", "h5py")),
        ("import tissuecli.cli.base", ("numpy", "h5py", "serial")),
    ],
)
def test_commands_load_only_what_they_use(code: str, absent: tuple[str, ...]) -> None:
    probe = f"{code}; import sys; print(' '.join(m for m in {absent!r} if m in sys.modules))"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == [], f"{code} loaded {out}"


#: test modules about the project as a whole rather than one subpackage
CROSS_CUTTING = {"test_architecture.py", "test_bench.py", "test_docs.py", "test_reliability.py"}


def test_tests_mirror_the_package() -> None:
    """A subpackage's tests live in the folder of the same name under tests/; only the
    whole-project checks stay at the top."""
    subpackages = {p.parent.name for p in (ROOT / "tissuecli").glob("*/__init__.py")}
    misplaced = []
    for path in (ROOT / "tests").rglob("test_*.py"):
        where = path.relative_to(ROOT / "tests").parts
        if len(where) == 1 and where[0] in CROSS_CUTTING:
            continue
        if len(where) != 2 or where[0] not in subpackages:
            misplaced.append(str(path.relative_to(ROOT)))
    assert not misplaced, f"tests outside tests/<subpackage>/: {misplaced}"
    folders = {p.name for p in (ROOT / "tests").iterdir() if p.is_dir() and p.name[0] not in "._"}
    assert folders <= subpackages, f"test folders with no subpackage: {folders - subpackages}"
