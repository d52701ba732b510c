"""softbody.compilation: a first run compiles the kernels in a background process while the numpy code runs, and
switches to the kernels without compiling any itself; a warm cache serves them from the first step; the stamps,
the lock and a failed warm-up behave."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import types
import warnings
from pathlib import Path

import pytest

from softbody import compilation, kernels

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")

# a scene in a child process under the default mode, counting numba's compilations in that process
CHILD = textwrap.dedent("""
    import json, sys, time
    from numba.core import event
    compiled = []
    class Listener(event.Listener):
        def on_start(self, e): pass
        def on_end(self, e): compiled.append(e.data["dispatcher"].py_func.__name__)
    event.register("numba:compile", Listener())
    from softbody import compilation, kernels
    from integration import kernels as contact_kernels
    from experiments.scenes import cubes_on_plane, sheet_on_sphere
    scenes = [sheet_on_sphere("tet10", (6, 6, 2)), cubes_on_plane("tet10", (2, 2, 2), count=2)]
    start = [kernels.ENABLED, contact_kernels.ENABLED, compilation.pending]
    reference = sheet_on_sphere("tet4", (4, 4, 2))  # 40 steps as the run starts: numpy's on a first run
    for _ in range(40):
        reference.world.step()
    numpy_steps, tic = 0, time.monotonic()
    while compilation.pending and time.monotonic() - tic < float(sys.argv[1]):
        scenes[0].world.step()  # the numpy code, while the warm-up compiles on the other core
        numpy_steps += 1
        time.sleep(0.02)
    switched = [kernels.ENABLED, contact_kernels.ENABLED, compilation.pending]
    for scene in scenes:
        for _ in range(30):
            scene.world.step()
    print(json.dumps({"start": start, "switched": switched, "numpy_steps": numpy_steps, "compiled": compiled,
                      "z": reference.monitored()}))
""")


def _child(cache: Path, wait: float = 0.0) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), SOFTBODY_COMPILE="background", OMP_NUM_THREADS="1",
               MKL_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", CHILD, str(wait)], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=900)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def first_run(tmp_path_factory) -> tuple[Path, dict]:
    """A first run on an empty cache, stepping the numpy code until the background warm-up ends."""
    cache = tmp_path_factory.mktemp("numba-cache")
    return cache, _child(cache, wait=600.0)


def test_a_first_run_steps_the_numpy_code_while_a_background_process_compiles(first_run):
    cache, out = first_run
    assert out["start"] == [False, False, True]  # empty cache: the numpy code, a warm-up pending
    assert out["numpy_steps"] >= 1
    assert out["switched"] == [True, True, False]  # the warm-up ended: the kernels, from the cache
    assert out["compiled"] == []  # this process compiled nothing, before the switch or after it
    assert not list(cache.rglob("softbody-warmup.lock"))
    stamps = sorted(p.name for p in cache.rglob("*.softbody-warm"))
    assert stamps == ["cholesky.py.softbody-warm", "kernels.py.softbody-warm", "kernels.py.softbody-warm"]


def test_a_warm_cache_serves_the_kernels_from_the_first_step(first_run):
    cache, first = first_run
    out = _child(cache)
    assert out["start"] == [True, True, False]
    assert out["numpy_steps"] == 0
    assert out["compiled"] == []  # the warm-up covered both scenes: every kernel came from the cache
    assert out["z"] == pytest.approx(first["z"], abs=1e-9)  # the same 40 steps by the numpy code and by the kernels


@pytest.fixture
def fake(tmp_path, monkeypatch):
    """compilation's registry holding one fake kernel module: its source a temporary file, its cache directory
    another (as a numba dispatcher's ``_cache._cache_path``)."""
    source = tmp_path / "fake_kernels.py"
    source.write_text("x = 1\n")
    cache = tmp_path / "cache"
    module = types.ModuleType("fake_kernels")
    module.__file__ = str(source)
    def kernel():
        pass

    kernel.__module__ = module.__name__  # a kernel defined in the module, cached in ``cache``
    module.kernel = types.SimpleNamespace(_cache=types.SimpleNamespace(_cache_path=str(cache)), py_func=kernel)
    module.ENABLED = True
    monkeypatch.setattr(compilation, "_modules", [])
    monkeypatch.setattr(compilation, "MODE", "background")
    monkeypatch.setattr(compilation, "pending", False)
    monkeypatch.setattr(compilation, "_process", None)
    monkeypatch.setattr(compilation, "_next_check", 0.0)
    monkeypatch.setattr(compilation, "_rounds", 0)
    return module, source, cache


def test_a_stamp_holds_until_the_source_changes(fake):
    module, source, cache = fake
    assert compilation.register(module, True) is False  # no stamp yet: cold
    assert compilation.pending and module.ENABLED is False
    compilation.stamp()
    assert compilation.cache_is_warm()
    source.write_text("x = 22\n")  # an edited kernel module: numba recompiles it, so the stamp no longer holds
    assert not compilation.cache_is_warm()


@pytest.mark.skipif(os.name == "nt", reason="no pid probe on Windows: a lock's age decides there")
def test_the_lock_keeps_one_warm_up_and_outlives_no_dead_holder(fake):
    _, _, cache = fake
    compilation.register(fake[0], True)
    lock = compilation._lock_path()
    assert Path(lock).parent == cache
    fd = compilation._take_lock(lock)
    assert fd is not None
    os.write(fd, str(os.getpid()).encode())  # held by a live process (this one)
    os.close(fd)
    assert compilation._take_lock(lock) is None
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    Path(lock).write_text(dead.stdout.strip())  # held by a process that has ended: taken over
    fd = compilation._take_lock(lock)
    assert fd is not None
    os.close(fd)
    Path(lock).write_text(str(os.getpid()))  # a live holder, but an abandoned lock: older than LOCK_MAX_AGE
    old = time.time() - compilation.LOCK_MAX_AGE - 1
    os.utime(lock, (old, old))
    fd = compilation._take_lock(lock)
    assert fd is not None
    os.close(fd)


def test_a_failed_warm_up_warns_and_leaves_the_numpy_code_running(fake, monkeypatch):
    module, _, cache = fake
    compilation.register(module, True, warmup="softbody.no_such_warm_up")
    monkeypatch.setattr(compilation, "_warmup_module", "softbody.no_such_warm_up")
    compilation.poll()  # starts the warm-up, which fails at once
    assert compilation._process is not None
    compilation._process.wait(timeout=60)
    with pytest.warns(RuntimeWarning, match="background compilation ended with code 1"):
        compilation.poll()
    assert compilation.pending is False and module.ENABLED is False
    assert "no_such_warm_up" in (cache / "softbody-warmup.log").read_text()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        compilation.poll()  # said once


def test_a_warm_up_that_stamps_nothing_is_tried_twice_then_given_up(fake, monkeypatch):
    module, _, _ = fake
    compilation.register(module, True)
    monkeypatch.setattr(compilation, "_warmup_module", "this")  # python -m this: exits 0, compiles nothing
    compilation.poll()  # the first warm-up
    compilation._process.wait(timeout=60)
    compilation.poll()  # it ended well, the cache still cold: a second
    assert compilation._rounds == 2
    compilation._process.wait(timeout=60)
    with pytest.warns(RuntimeWarning, match="did not cover every kernel module"):
        compilation.poll()
    assert compilation._rounds == 2 and compilation.pending is False and module.ENABLED is False


def test_softbody_compile_fills_the_cache(tmp_path):
    """The command line's foreground warm-up (tested on the FEM core's: the same path, fewer kernels)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), SOFTBODY_COMPILE="background")
    code = ("from softbody import compilation, kernels; assert compilation.pending; "
            "compilation.compile_now(); assert kernels.ENABLED and not compilation.pending")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.rglob("*.softbody-warm")) == ["cholesky.py.softbody-warm",
                                                                        "kernels.py.softbody-warm"]


def test_the_auto_solver_backend_is_chosen_again_when_the_kernels_switch_on(monkeypatch):
    """A first run makes its solvers before the kernels are ready: "auto" then takes PARDISO (or SuperLU) where the
    small systems' block Cholesky (compiled) would serve; at the switch it chooses again."""
    from softbody import FemBody, LinearElastic, box_mesh
    from softbody.solvers import BodySolvers

    body = FemBody(box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet4"), LinearElastic(1e5, 0.3, 1000.0))
    solvers = BodySolvers()
    monkeypatch.setattr(kernels, "ENABLED", False)
    first = solvers.solver(body, "auto")
    pinned = solvers.solver(body, "superlu")
    assert first.backend in ("pardiso", "superlu") and solvers.solver(body, "auto") is first
    monkeypatch.setattr(kernels, "ENABLED", True)
    monkeypatch.setattr(compilation, "switches", compilation.switches + 1)  # as compilation.poll does
    again = solvers.solver(body, "auto")
    assert again is not first and again.backend == "blocks"
    assert solvers.solver(body, "superlu") is pinned  # a backend the user named stays


def test_an_unwritable_cache_warns_and_leaves_the_numpy_code_running(fake, tmp_path):
    module, _, _ = fake
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    module.kernel._cache._cache_path = str(blocker / "cache")  # a directory that cannot be made
    assert compilation.register(module, True) is False
    with pytest.warns(RuntimeWarning, match="cannot write numba's cache directory"):
        compilation.poll()
    assert compilation.pending is False and compilation._process is None and module.ENABLED is False


def test_kernels_without_a_disk_cache_wait_for_nothing(fake):
    """E.g. NUMBA_DISABLE_JIT: the kernels are plain functions, nothing to compile, no cache to fill."""
    module, _, _ = fake
    del module.kernel
    assert compilation.register(module, True) is True
    assert compilation.pending is False


@pytest.mark.skipif(os.name == "nt", reason="waitpid and SIGKILL: POSIX")
def test_a_warm_up_running_at_exit_is_left_to_finish_without_a_resource_warning(monkeypatch):
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        monkeypatch.setattr(compilation, "_process", child)
        compilation._leave_running()
        assert child.returncode == 0  # Popen's __del__ then says nothing of it
        assert child.poll() == 0 and os.waitpid(child.pid, os.WNOHANG) == (0, 0)  # and it still runs
    finally:
        os.kill(child.pid, signal.SIGKILL)  # (Popen.kill sends nothing once returncode is set)
        os.waitpid(child.pid, 0)


def test_timed_commands_fill_a_cold_cache_first(fake, monkeypatch):
    module, _, _ = fake
    compilation.register(module, True)
    ran, said = [], []
    monkeypatch.setattr(compilation, "compile_now", lambda: ran.append(True) or 1.0)
    compilation.ensure_ready(said.append)
    assert ran == [True] and "compiling softbody's kernels" in said[0]
    monkeypatch.setattr(compilation, "pending", False)
    compilation.ensure_ready(said.append)  # a warm cache: nothing to do
    assert ran == [True] and len(said) == 1
