"""When the compiled kernels are used: at once from numba's disk cache, or after a background compilation.

numba compiles a kernel at its first call and caches it on disk. Compiling what one scene uses takes about 15 s
of CPU (the sheet-on-sphere scene's kernels: about 36 functions at 0.1-1.5 s each; every kernel with every
argument type of the warm-up's scenes about 40 s), which a fresh install's first run would otherwise wait for at
its first steps. Instead, when the cache does not hold this
version of the kernels, the first step starts one background process (``python -m <warm-up module>``, e.g.
``integration.warmup``) that runs small scenes through the kernels (every element type, linear method and contact
kind) and so fills the cache, and the numpy code
(the kernels' reference, the same arithmetic to round-off) runs meanwhile. The step after that process ends
switches to the kernels, loading them from the cache (a few tenths of a second). Later runs find the cache
filled and use the kernels from their first step.

Whether the cache holds this version is a stamp per kernel module (source file mtime and size, numba's and
Python's versions, the CPU numba compiles for, as numba's own cache index keys them), written by the warm-up
process next to numba's own cache files once its scenes ran through. A lock file there keeps concurrent first
runs (a sweep's workers) to one warm-up process; a lock whose process is gone, or older than LOCK_MAX_AGE, is
taken over.

``SOFTBODY_COMPILE=now`` compiles in-process at first use instead (the tests do: a test that compares a
kernel with its numpy code must know which one runs); ``softbody compile`` (experiments.cli) fills the cache
in the foreground, e.g. when building an image.
"""
from __future__ import annotations

import atexit
import contextlib
import json
import os
import subprocess
import sys
import time
import warnings
from types import ModuleType
from typing import Callable

try:
    import numba
except ImportError:  # pragma: no cover - numba is installed with the package
    numba = None

#: "background" (default) or "now", from SOFTBODY_COMPILE
MODE = os.environ.get("SOFTBODY_COMPILE", "background").strip().lower() or "background"
if MODE not in ("background", "now"):
    raise ValueError(f"SOFTBODY_COMPILE={MODE!r}: expected 'background' or 'now'")
#: seconds between two looks at another process's warm-up
CHECK_EVERY = 1.0
#: seconds after which a warm-up's lock counts as abandoned whatever its process (the warm-up takes about 40 s)
LOCK_MAX_AGE = 600.0

#: True while the kernels wait for a warm-up (softbody.simulation polls then, once per step)
pending = False
_modules: list[tuple[ModuleType, str]] = []  # (module with an ENABLED flag, its source file)
_warmup_module = "softbody.warmup"
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the checkout holding softbody/ (warm-up's cwd)
_process: subprocess.Popen | None = None
_next_check = 0.0
_rounds = 0  # warm-up processes this process started
#: how many times the kernels were switched on here (a choice made without them, e.g. a solver backend, is redone)
switches = 0


def _cache_dir(module: ModuleType) -> str | None:
    """The directory numba caches ``module``'s own kernels in (None: no cached kernel defined in it, e.g. under
    NUMBA_DISABLE_JIT)."""
    for value in vars(module).values():
        cache = getattr(value, "_cache", None)
        defined_here = getattr(getattr(value, "py_func", None), "__module__", None) == module.__name__
        if defined_here and cache is not None and hasattr(cache, "_cache_path"):
            return cache._cache_path
    return None


def _stamp_path(source: str, module: ModuleType) -> str | None:
    directory = _cache_dir(module)
    if directory is None:
        return None
    return os.path.join(directory, os.path.basename(source) + ".softbody-warm")


def _cpu() -> str:
    """The CPU name and features numba compiles for (part of its cache index's key)."""
    try:
        from llvmlite import binding

        name = os.environ.get("NUMBA_CPU_NAME") or binding.get_host_cpu_name()
        features = os.environ.get("NUMBA_CPU_FEATURES") or binding.get_host_cpu_features().flatten()
        return f"{name} {features}"
    except Exception:  # noqa: BLE001 - an llvmlite without these: the versions alone
        return ""


def _identity(source: str) -> dict[str, object]:
    """What a stamp records of a kernel module's source and of the compiler."""
    st = os.stat(source)
    return {"numba": getattr(numba, "__version__", ""), "python": sys.version.split()[0], "cpu": _cpu(),
            "mtime": st.st_mtime, "size": st.st_size}


def _is_warm(source: str, module: ModuleType) -> bool:
    path = _stamp_path(source, module)
    try:
        with open(path) as f:
            return json.load(f) == _identity(source)
    except (OSError, TypeError, ValueError):
        return False


def cache_is_warm() -> bool:
    """Whether numba's cache holds every registered kernel module as it is now (stamped by a warm-up)."""
    return all(_is_warm(source, module) for module, source in _modules if _stamp_path(source, module) is not None)


def stamp(identities: dict[str, dict] | None = None) -> None:
    """Mark every registered kernel module as compiled into the cache (the warm-up's last act); ``identities``
    {source: _identity} as read before the warm-up ran (a source edited meanwhile stays unstamped)."""
    for module, source in _modules:
        path = _stamp_path(source, module)
        if path is None:
            continue
        identity = (identities or {}).get(source) or _identity(source)
        if identity != _identity(source):
            continue
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}"
        with open(tmp, "w") as f:
            json.dump(identity, f)
        os.replace(tmp, path)


def _set_enabled(flag: bool) -> None:
    """Set the ENABLED flag of every registered kernel module (read at each call site)."""
    global switches
    for module, _ in _modules:
        module.ENABLED = flag
    switches += flag


def register(module: ModuleType, available: bool, warmup: str | None = None) -> bool:
    """Register a module of kernels (its ``ENABLED`` flag follows this module's decision) and, optionally, the
    warm-up module that compiles it (the last registered runs: it must cover the earlier ones). Returns the
    module's starting ENABLED: available and, in background mode, the cache warm."""
    global pending, _warmup_module
    _modules.append((module, module.__file__))
    if warmup is not None:
        _warmup_module = warmup
    if not available or MODE == "now" or _stamp_path(module.__file__, module) is None:
        return available  # nothing to wait for (or no cache to fill): compiled at first use, if at all
    if not pending and cache_is_warm():
        return True
    pending = True
    _set_enabled(False)
    return False


def _lock_path() -> str | None:
    """The warm-up's lock file, beside the first registered module's cached kernels (None: no disk cache)."""
    for module, source in _modules:
        directory = _cache_dir(module)
        if directory is not None:
            return os.path.join(directory, "softbody-warmup.lock")
    return None


def _alive(pid: int, path: str) -> bool:
    """Whether the warm-up process ``pid`` (holding the lock file ``path``) may still run: its lock is younger than
    LOCK_MAX_AGE and, on POSIX, a process of that pid exists."""
    if time.time() - os.path.getmtime(path) > LOCK_MAX_AGE:
        return False
    if os.name == "nt":  # os.kill(pid, 0) would end the process there: the age decides
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _take_lock(path: str) -> int | None:
    """Create the lock file (None if another live process holds it)."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    for _ in range(2):
        try:
            return os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                with open(path) as f:
                    holder = int(f.read().strip() or 0)
            except (OSError, ValueError):
                holder = 0
            if holder and _alive(holder, path):
                return None
            if not holder and time.time() - os.path.getmtime(path) < 5.0:
                return None  # just created, its pid not written yet
            try:
                os.remove(path)  # left by a warm-up that died
            except FileNotFoundError:
                pass
    return None


def _child_env(**extra: str) -> dict[str, str]:
    """The environment of a warm-up child: this one, this checkout first on the path, kernels compiled in-process."""
    return dict(os.environ, SOFTBODY_COMPILE="now", **extra,
                PYTHONPATH=os.pathsep.join(p for p in (_ROOT, os.environ.get("PYTHONPATH", "")) if p))


def _start() -> None:
    """Start the warm-up process unless another process runs one (an unwritable cache: a warning, the numpy code)."""
    global _process, _rounds
    lock = _lock_path()
    if lock is None:
        _give_up("no numba cache directory for the kernels")
        return
    try:
        fd = _take_lock(lock)
    except OSError as error:
        _give_up(f"cannot write numba's cache directory ({error})")
        return
    if fd is None:
        return  # another process's warm-up: poll() watches the stamps
    detach = ({"creationflags": subprocess.DETACHED_PROCESS | subprocess.CREATE_NEW_PROCESS_GROUP} if os.name == "nt"
              else {"start_new_session": True})  # the warm-up outlives this run, and its Ctrl+C
    try:
        with open(os.path.join(os.path.dirname(lock), "softbody-warmup.log"), "w") as log:
            _process = subprocess.Popen([sys.executable, "-m", _warmup_module], stdin=subprocess.DEVNULL, stdout=log,
                                        stderr=subprocess.STDOUT, env=_child_env(SOFTBODY_WARMUP_LOCK=lock),
                                        cwd=_ROOT, **detach)
        os.write(fd, str(_process.pid).encode())
    except OSError as error:
        with contextlib.suppress(OSError):
            os.remove(lock)
        _give_up(f"could not start the background compilation ({error})")
        return
    finally:
        os.close(fd)
    _rounds += 1
    atexit.register(_leave_running)


def _leave_running() -> None:
    """At exit: a warm-up still running is left to finish (it outlives this run on purpose, in its own session),
    without Popen's ResourceWarning about it."""
    if _process is not None and _process.poll() is None:
        _process.returncode = 0


def _release_lock(holder: str) -> None:
    """Remove the warm-up lock if ``holder`` (a pid, as text; "" too) holds it: a warm-up that ended without
    removing it (killed, or not ours)."""
    lock = _lock_path()
    try:
        with open(lock) as f:
            if f.read().strip() in ("", holder):
                os.remove(lock)
    except (OSError, TypeError):
        pass


def _give_up(why: str) -> None:
    global pending
    pending = False
    warnings.warn(f"softbody: {why}; the numpy code runs (SOFTBODY_COMPILE=now compiles in-process)", RuntimeWarning,
                  stacklevel=3)


def poll() -> None:
    """Called once per step while :data:`pending`: start the warm-up if nobody runs one, switch to the kernels once
    the cache is warm (looking at another process's warm-up every CHECK_EVERY seconds)."""
    global pending, _process, _next_check
    if not pending:
        return
    if _process is not None:
        code = _process.poll()
        if code is None:
            return
        _release_lock(str(_process.pid))
        _process = None
        if code != 0:
            _give_up(f"the background compilation ended with code {code} (log: "
                     f"{os.path.join(os.path.dirname(_lock_path() or ''), 'softbody-warmup.log')})")
            return
        _next_check = 0.0  # look now
    now = time.monotonic()
    if now < _next_check:
        return
    _next_check = now + CHECK_EVERY
    if cache_is_warm():
        pending = False
        _set_enabled(True)
    elif _rounds >= 2:  # warm-ups ended well twice and left kernel modules unstamped (one imported after them?)
        _give_up("the background compilation did not cover every kernel module")
    else:
        _start()


def compile_now() -> float:
    """Fill the cache in the foreground: the warm-up module in a child process, waited for. Returns its seconds;
    raises RuntimeError with the child's output if it fails or leaves a kernel module unstamped."""
    global pending
    tic = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", _warmup_module], stdin=subprocess.DEVNULL, capture_output=True,
                          text=True, env=_child_env(), cwd=_ROOT)
    if done.returncode != 0:
        raise RuntimeError(f"python -m {_warmup_module} failed (code {done.returncode}):\n{done.stdout}{done.stderr}")
    if not cache_is_warm():
        raise RuntimeError(f"python -m {_warmup_module} ran but left kernel modules unstamped (an edit meanwhile?): "
                           f"{[source for module, source in _modules if not _is_warm(source, module)]}")
    if pending:
        pending = False
        _set_enabled(True)
    return time.perf_counter() - tic


def ensure_ready(say: Callable[[str], object] = print) -> None:
    """Before timed runs (bench, studies, sweeps): if the kernels wait for a warm-up, fill the cache in the foreground
    now (saying so through ``say``), so that no timing is the numpy code's."""
    if pending:
        say("# compiling softbody's kernels into numba's cache first (once after an install, about 40 s) ...")
        compile_now()


def warm_up(run: Callable[[], object]) -> None:
    """The warm-up process's body: ``run()`` (scenes through the kernels, compiling in-process), then the stamps of
    the sources as they were before it; the lock (if this process was started under one) is removed whatever
    happens."""
    background = bool(os.environ.get("SOFTBODY_WARMUP_LOCK"))
    if background and hasattr(os, "nice"):
        os.nice(10)  # behind the run that started it, which steps meanwhile
    try:
        identities = {source: _identity(source) for _, source in _modules}
        run()
        stamp(identities)
    finally:
        if os.environ.get("SOFTBODY_WARMUP_LOCK") == _lock_path():
            _release_lock(str(os.getpid()))
