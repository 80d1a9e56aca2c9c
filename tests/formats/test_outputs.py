"""No output destroys a file: every output option refuses an existing file unless
--force, refuses one of the command's inputs always, and is checked before the work."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.cli import cli
from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.formats.jsonfile import write_json
from tissuecli.formats.params import tissue_to_dict
from tissuecli.formats.sessions import write_session
from tissuecli.sim.synth import ForcepsModel, synthesize

from ..conftest import assert_clean_error


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def _inputs(root: Path) -> tuple[Path, Path]:
    """A session file and a parameter file, as a user has them."""
    s, _ = synthesize(ForcepsModel(seed=2), 2.0)
    s.name = "s"
    write_session(root / "grasp.h5", s)
    write_json(root / "tissue.json", tissue_to_dict(DEFAULT_TISSUE))
    return root / "grasp.h5", root / "tissue.json"


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return _inputs(tmp_path_factory.mktemp("inputs"))


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


#: every whole-file output: the command line (OUT stands for the output path) and the
#: option's name; play needs no display, as outputs are checked before the port opens
COMMANDS = {
    "fit --out": ("fit", "{h5}", "--out", "OUT"),
    "fit --report": ("fit", "{h5}", "--report", "OUT"),
    "export --csv": ("export", "{h5}", "--csv", "OUT"),
    "play --check --summary": ("play", "{params}", "--check", "--summary", "OUT"),
    "play --summary": ("play", "{params}", "--port", "/nonexistent/port", "--summary", "OUT"),
}


def _argv(name: str, h5: Path, params: Path, out: Path) -> list[str]:
    return [str(out) if a == "OUT" else a.format(h5=h5, params=params) for a in COMMANDS[name]]


@pytest.mark.parametrize("name", COMMANDS)
def test_an_existing_output_is_refused_and_kept(name: str, files, tmp_path: Path) -> None:
    h5, params = files
    out = tmp_path / "precious.txt"
    out.write_text("keep me")
    result = run(*_argv(name, h5, params, out))
    assert_clean_error(result, "exists", "--force")
    assert out.read_text() == "keep me"


@pytest.mark.parametrize("name", COMMANDS)
@pytest.mark.parametrize("link", ["same", "symlink", "hardlink"])
def test_an_input_is_never_an_output_even_with_force(
    name: str, link: str, files, tmp_path: Path
) -> None:
    h5, params = files
    target = params if name.startswith("play") else h5
    before = _digest(target)
    out = tmp_path / "alias"
    if link == "same":
        out = target
    elif link == "symlink":
        out.symlink_to(target)
    else:
        os.link(target, out)
    result = run(*_argv(name, h5, params, out), "--force")
    assert_clean_error(result, "input file")
    assert _digest(target) == before


@pytest.mark.parametrize("name", COMMANDS)
def test_a_missing_directory_is_refused_before_the_work(name: str, files, tmp_path) -> None:
    h5, params = files
    result = run(*_argv(name, h5, params, tmp_path / "missing" / "out.txt"))
    assert_clean_error(result, "does not exist")


def test_fit_writes_nothing_when_one_of_its_outputs_cannot_be_written(files, tmp_path) -> None:
    h5, _ = files
    out = tmp_path / "p.json"
    result = run("fit", h5, "--out", out, "--report", tmp_path / "missing" / "r.html")
    assert_clean_error(result, "--report")
    assert not out.exists()
    assert_clean_error(run("fit", h5, "--out", out, "--report", out), "same file")


def test_force_replaces_keeping_permissions_and_not_following_links(files, tmp_path) -> None:
    h5, _ = files
    out = tmp_path / "p.json"
    out.write_text("old")
    out.chmod(0o600)
    assert run("fit", h5, "--out", out, "--force").exit_code == 0
    assert out.read_text().startswith("{") and (out.stat().st_mode & 0o777) == 0o600
    victim = tmp_path / "victim"
    victim.write_text("victim")
    link = tmp_path / "link.json"
    link.symlink_to(victim)
    assert run("fit", h5, "--out", link, "--force").exit_code == 0
    assert victim.read_text() == "victim" and not link.is_symlink()


def test_planted_temporary_names_are_not_followed(files, tmp_path) -> None:
    h5, _ = files
    victim = tmp_path / "victim"
    victim.write_text("victim")
    for planted in ("p.json.tmp", ".p.json.tmp", "r.html.part"):
        (tmp_path / planted).symlink_to(victim)
    assert (
        run("fit", h5, "--out", tmp_path / "p.json", "--report", tmp_path / "r.html").exit_code == 0
    )
    assert victim.read_text() == "victim"
    assert sorted(p.name for p in tmp_path.iterdir() if not p.is_symlink()) == [
        "p.json",
        "r.html",
        "victim",
    ]


def test_demo_keeps_the_files_of_an_earlier_demo(tmp_path) -> None:
    (tmp_path / "tissue.json").write_text("mine")
    assert_clean_error(run("demo", "--dir", tmp_path), "tissue.json", "--force")
    assert (tmp_path / "tissue.json").read_text() == "mine"


RELATIONS = ("new", "existing", "input", "symlink to input", "symlink to other", "missing dir")


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    name=st.sampled_from(sorted(COMMANDS)),
    relation=st.sampled_from(RELATIONS),
    force=st.booleans(),
)
def test_outputs_never_destroy_a_file(files, name: str, relation: str, force: bool) -> None:
    """Whatever the output names and whether --force is given: inputs are unchanged, a
    file the user did not ask to replace is unchanged, and a refusal is one line, exit 1."""
    h5, params = files
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        other = root / "other.txt"
        other.write_text("other")
        out = {
            "new": root / "new.txt",
            "existing": other,
            "input": params if name.startswith("play") else h5,
            "symlink to input": root / "link",
            "symlink to other": root / "link",
            "missing dir": root / "missing" / "x.txt",
        }[relation]
        if relation == "symlink to input":
            out.symlink_to(params if name.startswith("play") else h5)
        elif relation == "symlink to other":
            out.symlink_to(other)
        before = {p: _digest(p) for p in (h5, params, other)}
        # the law search bears on no output (the fits above and below run it): one form
        quick = ["--forms", "x,xdot"] if name.startswith("fit") else []
        result = run(*_argv(name, h5, params, out), *quick, *(["--force"] if force else []))
        after = {p: _digest(p) for p in (h5, params, other)}
        assert after[h5] == before[h5] and after[params] == before[params]
        if not (force and relation == "existing"):
            assert after[other] == before[other]
        if result.exit_code != 0:
            assert_clean_error(result)


#: outputs that gain a group (appended to): they too must be regular files
APPENDING = {
    "record --out": ("record", "--port", "/nonexistent/port", "--out", "OUT"),
    "import --out": ("import", "{csv}", "--out", "OUT"),
    "play --log": ("play", "{params}", "--port", "/nonexistent/port", "--log", "OUT"),
}


def _special(kind: str, path: Path) -> str:
    """Make `path` a FIFO or a dangling link; the words the refusal must use."""
    if kind == "fifo":
        os.mkfifo(path)
        return "is a named pipe (FIFO), not a regular file"
    os.symlink(path.parent / "nowhere" / "file", path)
    return "is a symbolic link to"


@pytest.mark.parametrize("kind", ["fifo", "dangling"])
@pytest.mark.parametrize("name", [*COMMANDS, *APPENDING])
def test_a_fifo_or_a_dangling_link_is_refused_in_one_line_before_work(
    name: str, kind: str, files, tmp_path: Path
) -> None:
    """Without this, writing to a FIFO waits for a reader forever and a dangling link
    creates the file wherever it points; either is refused at once, --force or not."""
    from ..conftest import tissuecli

    h5, params = files
    csv = tmp_path / "in.csv"
    csv.write_text("time,force,position\n0,0,0\n0.001,0.1,0.0001\n")
    out = tmp_path / "out"
    words = _special(kind, out)
    argv = COMMANDS.get(name) or APPENDING[name]
    argv = [str(out) if a == "OUT" else a.format(h5=h5, params=params, csv=csv) for a in argv]
    result = tissuecli(*argv, *(["--force"] if name in COMMANDS else []), timeout=30)
    assert_clean_error(result, words)
    assert not (tmp_path / "nowhere").exists()


def test_a_device_is_refused_as_an_output(files) -> None:
    _, params = files
    result = run("play", params, "--check", "--summary", "/dev/null", "--force")
    assert_clean_error(result, "/dev/null is a character device, not a regular file")
