"""The examples' re-execution under glibc malloc tunables (``torchrl_dalir.allocator``)."""

import os
import platform
import subprocess
import sys
import textwrap

import pytest

from torchrl_dalir.allocator import MALLOC_TUNABLES, SWITCH, tuned_environment

glibc_linux = pytest.mark.skipif(
    sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc tunables only"
)


def untuned_environment() -> dict[str, str]:
    """This process's environment without the tunables or the switch, as a user's shell would have it."""
    return {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", SWITCH)}


@glibc_linux
def test_tuned_environment_adds_the_tunables_once_unless_turned_off():
    on = {"PATH": "/bin"}  # the default
    assert tuned_environment(on) == {**on, "GLIBC_TUNABLES": MALLOC_TUNABLES}
    assert tuned_environment({**on, SWITCH: "reuse"}) == {**on, SWITCH: "reuse", "GLIBC_TUNABLES": MALLOC_TUNABLES}
    # the user's other tunables are kept
    assert (
        tuned_environment({**on, "GLIBC_TUNABLES": "glibc.cpu.x86_shstk=off"})["GLIBC_TUNABLES"]
        == f"glibc.cpu.x86_shstk=off:{MALLOC_TUNABLES}"
    )
    # already set (by the user or by the re-execution itself): nothing to do
    assert tuned_environment({**on, "GLIBC_TUNABLES": MALLOC_TUNABLES}) is None
    assert tuned_environment({**on, "GLIBC_TUNABLES": "glibc.malloc.mmap_threshold=1"}) is None
    # turned off: glibc's defaults
    assert tuned_environment({**on, SWITCH: "system"}) is None


@glibc_linux
@pytest.mark.parametrize("tuned", [True, False])
def test_a_script_re_executes_once_with_its_arguments_unless_turned_off(tmp_path, tuned):
    script = tmp_path / "script.py"
    script.write_text(
        textwrap.dedent("""
        import os, sys
        print("start", os.getpid(), flush=True)
        from torchrl_dalir.allocator import reuse_freed_memory
        reuse_freed_memory(__file__)
        print("main", os.getpid(), sys.argv[1:], os.environ.get("GLIBC_TUNABLES"), flush=True)
    """)
    )
    env = untuned_environment()
    if not tuned:
        env[SWITCH] = "system"
    out = subprocess.run(
        [sys.executable, "-u", str(script), "a=1", "b=[2,3]"], env=env, capture_output=True, text=True, check=True
    ).stdout.split("\n")
    starts = [line for line in out if line.startswith("start")]
    mains = [line for line in out if line.startswith("main")]
    pid = starts[0].split()[1]
    assert len(mains) == 1 and mains[0].startswith(
        f"main {pid} ['a=1', 'b=[2,3]']"
    )  # the same process (execve), the same arguments
    if not tuned:
        assert len(starts) == 1 and mains[0].endswith("None")
    else:
        assert starts == [f"start {pid}"] * 2 and mains[0].endswith(MALLOC_TUNABLES)


@glibc_linux
def test_a_script_run_inside_another_program_does_not_re_execute_it(tmp_path):
    """A test runner (here a launcher) that runs an example's ``__main__`` block in its own process keeps running."""
    script = tmp_path / "script.py"
    script.write_text(
        "from torchrl_dalir.allocator import reuse_freed_memory\nreuse_freed_memory(__file__)\nprint('ran')\n"
    )
    launcher = tmp_path / "launcher.py"
    launcher.write_text(
        "import os, runpy\nprint('launcher', os.getpid(), flush=True)\n"
        f"runpy.run_path({str(script)!r}, run_name='__main__')\nprint('after', flush=True)\n"
    )
    env = untuned_environment()
    out = subprocess.run(
        [sys.executable, "-u", str(launcher)], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out.count("launcher") == 1 and out[-2:] == ["ran", "after"]
