"""Long work in a separate worker process, on the Python that runs this code (``sys.executable``).

Blender does not support Python threads beside its main loop, and a fit that runs out of memory
must not take the user's session with it, so the fit runs in a child process that the caller
starts, feeds, watches and can end at once. No bpy here: the same primitive runs the numerical
core for the Blender operators, the command line's parallel stages and Blender's importers.

The parent (:class:`Worker`) and the child (``python -m artdef_addon.procs FOLDER``) talk through
a private temporary folder and the child's stdin, never through pickles:

- each call gets its own sub-folder holding its input arrays as ``.npy`` files
  (``allow_pickle=False``; the child maps them copy-on-write, so a large array is read from the
  page cache, not copied per process) and ``call.json`` (the function's name and JSON
  parameters). The parent announces the call by writing the sub-folder's name as one line on
  the child's stdin; an end of stdin (the parent is gone) ends the child;
- the child appends progress and log lines as JSON to the call's ``messages.jsonl``, which the
  parent reads from where it stopped without blocking (:meth:`Call.poll`);
- the result is written last, atomically: its arrays as ``.npy`` files, then ``result.json``
  (JSON values, or the exception's type and message);
- a child that ends without a result (a crash, a signal, an exit code), a call past its timeout,
  and a ``MemoryError`` under the memory limit (``resource.setrlimit(RLIMIT_AS)`` on Linux) each
  become one :class:`WorkerError` line; :meth:`Worker.kill` ends the child and every process it
  started (its process group) at once. :meth:`Worker.close` removes the folder whatever happened.

A called function is ``"package.module:name"`` taking ``(arrays, params, report)``: a dict of
arrays, a dict of JSON values and a :class:`Reporter`; it returns a dict of JSON values, or a pair
``(values, arrays)``. Its module is imported in the child (from ``paths`` and the parent's
``sys.path``), so it must be one of ours.

>>> with Worker() as w:                                                  # doctest: +SKIP
...     call = w.submit("artdef_addon.jobs:fit", {"vertices": v, ...}, {"links": 3})
...     while not call.done:
...         for message in call.poll(): ...                           # from a modal timer
...     values, arrays = call.result()
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

#: progress lines written at most this often while the stage stays the same (seconds)
PROGRESS_EVERY = 0.05
#: how long :meth:`Worker.kill` waits for the killed child to be reaped (seconds)
KILL_WAIT = 1.0
#: the core package as the child imports it: top-level, also where this process knows it as a
#: sub-package (``bl_ext.user_default.artdef.artdef_addon`` inside Blender)
CORE = os.path.basename(os.path.dirname(os.path.abspath(__file__)))


class WorkerError(Exception):
    """One line saying why a call gave no result. ``kind``: ``error`` (the function raised;
    ``type_name`` is its exception's class), ``memory`` (out of memory or over the memory limit),
    ``crashed`` (a fatal signal, or an exit without a result), ``killed`` (SIGKILL or SIGTERM from
    outside), ``timeout``, ``cancelled`` (:meth:`Worker.kill`)."""

    def __init__(self, kind: str, message: str, type_name: str = "", details: str = ""):
        super().__init__(message)
        self.kind, self.type_name, self.details = kind, type_name, details


# ---------------------------------------------------------------------------------------- parent

def _child_env(paths, inherit: bool = True) -> dict:
    """The child's environment: this core's parent folder first (so ``-m artdef_addon.procs``
    finds this very package, also inside an installed extension), then ``paths``, then (``inherit``)
    the folders on this process's ``sys.path`` (numpy, the extension's bundled scipy)."""
    core_parent = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    seen, order = set(), []
    for p in [core_parent, *paths, *(sys.path if inherit else ())]:
        p = os.path.abspath(p) if p else ""
        if p and p not in seen and os.path.isdir(p):
            seen.add(p)
            order.append(p)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(order)
    env.pop("PYTHONSTARTUP", None)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _signal_name(num: int) -> str:
    try:
        return signal.Signals(num).name
    except ValueError:
        return f"signal {num}"


def _gb(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GB" if nbytes >= 2**30 else f"{nbytes / 2**20:.0f} MB"


class Call:
    """One call submitted to a :class:`Worker`: poll it for messages, then take its result."""

    def __init__(self, worker: "Worker", folder: str, timeout: float | None):
        self.worker, self.folder, self.timeout = worker, folder, timeout
        self.started = time.monotonic()
        self._offset = 0
        self._partial = b""
        self._outcome = None           # (values, arrays) or a WorkerError, once known

    def poll(self) -> list:
        """The messages written since the last poll (dicts: ``{"progress": [stage, fraction]}``
        or ``{"log": text}``); never blocks. Afterwards :attr:`done` says whether the call ended."""
        out = self._read_messages()
        if self._outcome is None:
            self._outcome = self._check()
            if self._outcome is not None:
                out += self._read_messages()
        return out

    @property
    def done(self) -> bool:
        if self._outcome is None:
            self.poll()
        return self._outcome is not None

    def wait(self, on_message=None, interval: float = 0.05):
        """Block until the call ends, passing each message to ``on_message`` (which may return
        True to cancel: the worker is killed); returns :meth:`result`."""
        while True:
            for m in self.poll():
                if on_message is not None and on_message(m):
                    self.worker.kill()
                    self.poll()
                    break
            if self._outcome is not None:
                return self.result()
            try:
                self.worker.process.wait(interval)
            except subprocess.TimeoutExpired:
                pass

    def result(self):
        """``(values, arrays)`` of a finished call, or raises its :class:`WorkerError`."""
        if not self.done:
            raise RuntimeError("the call has not finished")
        if isinstance(self._outcome, WorkerError):
            raise self._outcome
        return self._outcome

    # -- internals
    def _read_messages(self) -> list:
        path = os.path.join(self.folder, "messages.jsonl")
        try:
            with open(path, "rb") as f:
                f.seek(self._offset)
                data = f.read()
        except FileNotFoundError:
            return []
        self._offset += len(data)
        data = self._partial + data
        lines = data.split(b"\n")
        self._partial = lines.pop()           # an unfinished last line waits for the next poll
        out = []
        for line in lines:
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
        return out

    def _check(self):
        """The outcome if the call has ended (a result file, a dead child, a timeout), else None."""
        w = self.worker
        path = os.path.join(self.folder, "result.json")
        if os.path.exists(path):
            return self._load(path)
        if w.killed:
            return WorkerError("cancelled", "cancelled")
        code = w.process.poll()
        if code is not None:
            if os.path.exists(path):            # written just before the child ended
                return self._load(path)
            return w.exit_error(code)
        if self.timeout is not None and time.monotonic() - self.started > self.timeout:
            w.kill()
            w.timed_out = True
            return WorkerError("timeout", f"the worker process took longer than {self.timeout:g} s "
                                          f"and was stopped")
        return None

    def _load(self, path):
        with open(path, encoding="utf-8") as f:
            reply = json.load(f)
        if not reply.get("ok"):
            if reply.get("memory"):
                limit = self.worker.memory_limit
                w = WorkerError("memory", "the worker process ran out of memory"
                                + (f" (its limit is {_gb(limit)})" if limit else "")
                                + (f": {reply['message']}" if reply.get("message") else ""),
                                "MemoryError")
                self.worker.kill()              # its state after a failed allocation is not trusted
                return w
            return WorkerError("error", reply.get("message") or reply.get("type", "error"),
                               reply.get("type", ""), reply.get("traceback", ""))
        arrays = {name: np.load(os.path.join(self.folder, f"out-{i}.npy"), allow_pickle=False)
                  for i, name in enumerate(reply.get("arrays", []))}
        return reply.get("values", {}), arrays


class Worker:
    """A child process on ``sys.executable`` (or ``interpreter``, an argv prefix that runs Python
    with ``-m``-style arguments after it) that runs our functions one call at a time.

    ``memory_limit``: bytes the child may map beyond what it holds after importing ``preload``
    (Linux: ``RLIMIT_AS``; elsewhere not enforced). ``paths``: folders put on the child's
    ``sys.path`` before the parent's. ``preload``: modules imported at start-up (their cost is
    paid once, not per call). ``env``: extra environment variables for the child. ``own_group``:
    the child leads its own process group (killed with everything it starts, and the terminal's
    Ctrl-C is the parent's); a :class:`Pool`'s workers stay in their parent's group instead, so
    that killing the parent's group ends them too. ``inherit_path``: False for a child that must
    find its own modules only (one with Blender: the parent's ``bpy`` folders would shadow its own)."""

    def __init__(self, *, memory_limit: float | None = None, paths=(), preload=(), interpreter=None,
                 env: dict | None = None, name: str = "artdef-worker", own_group: bool = True,
                 inherit_path: bool = True):
        self.memory_limit = None if memory_limit is None else float(memory_limit)
        self.paths, self.preload = list(paths), list(preload)
        self.interpreter = list(interpreter) if interpreter else [sys.executable]
        self.extra_env = dict(env or {})
        self.name = name
        self.own_group = own_group
        self.inherit_path = inherit_path
        self.folder = None
        self.process = None
        self.killed = False
        self.timed_out = False
        self._calls = 0
        self._log = None

    # -- life
    def start(self) -> "Worker":
        if self.process is not None:
            return self
        self.folder = tempfile.mkdtemp(prefix=f"{self.name}-")
        with open(os.path.join(self.folder, "worker.json"), "w", encoding="utf-8") as f:
            json.dump({"memory_limit": self.memory_limit, "preload": self.preload,
                       "parent": os.getpid()}, f)
        env = _child_env(self.paths, self.inherit_path)
        # the child's temporaries (Blender's session folder among them) go inside the worker's
        # folder, which close() removes whatever the child did: also after a crash or a kill
        tmp = os.path.join(self.folder, "tmp")
        os.mkdir(tmp)
        env.update({"TMPDIR": tmp, "TEMP": tmp, "TMP": tmp})
        env.update(self.extra_env)
        self._log = open(os.path.join(self.folder, "stderr.txt"), "wb")
        kw = {}
        if not self.own_group:
            pass
        elif os.name == "posix":
            kw["start_new_session"] = True
        else:
            kw["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
        try:
            self.process = subprocess.Popen(
                self.interpreter + ["-m", f"{CORE}.procs", self.folder], stdin=subprocess.PIPE,
                stdout=self._log, stderr=subprocess.STDOUT, cwd=self.folder, env=env, **kw)
        except BaseException:
            self.close()
            raise
        return self

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def kill(self) -> None:
        """End the child and every process it started, now; waits at most :data:`KILL_WAIT`."""
        p = self.process
        if p is None:
            return
        self.killed = True
        if p.poll() is None:
            try:
                if not self.own_group:
                    p.kill()
                elif os.name == "posix":
                    os.killpg(p.pid, signal.SIGKILL)
                else:
                    subprocess.run(["taskkill", "/F", "/T", "/PID", str(p.pid)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=KILL_WAIT)
            except (OSError, subprocess.SubprocessError):
                p.kill()
        try:
            p.wait(KILL_WAIT)
        except subprocess.TimeoutExpired:
            pass

    def close(self) -> None:
        """Kill the child if it still runs and remove the temporary folder."""
        if self.process is not None:
            if self.process.poll() is None:
                try:
                    self.process.stdin.close()       # an idle child ends on this
                except OSError:
                    pass
                try:
                    self.process.wait(0.2)
                except subprocess.TimeoutExpired:
                    self.kill()
            for stream in (self.process.stdin,):
                try:
                    stream.close()
                except OSError:
                    pass
        if self._log is not None:
            self._log.close()
            self._log = None
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
        return False

    # -- calls
    def submit(self, function: str, arrays: dict | None = None, params: dict | None = None,
               timeout: float | None = None) -> Call:
        """Hand ``arrays`` and ``params`` to ``function`` in the child; returns its :class:`Call`."""
        if ":" not in function:
            raise ValueError(f"function must be 'module:name', got {function!r}")
        self.start()
        if not self.alive():
            raise self.exit_error(self.process.poll())
        self._calls += 1
        name = f"call-{self._calls}"
        folder = os.path.join(self.folder, name)
        os.mkdir(folder)
        names = []
        for i, (key, a) in enumerate((arrays or {}).items()):
            a = np.asarray(a)
            if a.dtype.hasobject:
                raise ValueError(f"array {key!r} holds Python objects; only plain arrays are handed over")
            np.save(os.path.join(folder, f"in-{i}.npy"), a, allow_pickle=False)
            names.append(key)
        with open(os.path.join(folder, "call.json"), "w", encoding="utf-8") as f:
            json.dump({"function": function, "params": params or {}, "arrays": names}, f)
        try:
            self.process.stdin.write(name.encode() + b"\n")
            self.process.stdin.flush()
        except OSError:
            pass                                  # the child is gone: the call's poll says why
        return Call(self, folder, timeout)

    def exit_error(self, code: int) -> WorkerError:
        """The one line for a child that ended with ``code`` (negative: a signal) and no result."""
        if self.killed and not self.timed_out:
            return WorkerError("cancelled", "cancelled")
        tail = self.stderr_tail()
        if code < 0:
            sig = -code
            if sig == getattr(signal, "SIGKILL", None):
                return WorkerError("killed", "the worker process was killed (SIGKILL: stopped from outside, "
                                             "or the system ran out of memory)")
            if sig == signal.SIGTERM:
                return WorkerError("killed", "the worker process was terminated (SIGTERM)")
            return WorkerError("crashed", f"the worker process crashed ({_signal_name(sig)})"
                               + (f": {tail}" if tail else ""))
        if self.memory_limit and "memory" in tail.lower():
            return WorkerError("memory", f"the worker process ran out of memory (its limit is "
                                         f"{_gb(self.memory_limit)}): {tail}")
        if code == 0:
            return WorkerError("crashed", "the worker process ended without a result"
                               + (f": {tail}" if tail else ""))
        return WorkerError("crashed", f"the worker process exited with code {code}"
                           + (f": {tail}" if tail else ""))

    def stderr_tail(self) -> str:
        """The last non-empty line the child wrote to stdout/stderr ('' if none)."""
        if self.folder is None:
            return ""
        try:
            with open(os.path.join(self.folder, "stderr.txt"), "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - 4096))
                lines = [ln.strip() for ln in f.read().decode("utf-8", "replace").splitlines()]
        except OSError:
            return ""
        lines = [ln for ln in lines if ln]
        return lines[-1] if lines else ""


def run(function: str, arrays: dict | None = None, params: dict | None = None, *, on_message=None,
        timeout: float | None = None, **worker):
    """Start a worker, make one call, wait for it (``on_message`` as in :meth:`Call.wait`), clean
    up; returns ``(values, arrays)`` or raises :class:`WorkerError`."""
    with Worker(**worker) as w:
        return w.submit(function, arrays, params, timeout).wait(on_message)


# ------------------------------------------------------------------------------- a pool of workers

def cores() -> int:
    """The CPUs this process may use (the default of ``FitOptions.jobs``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:          # not on Linux
        return max(1, os.cpu_count() or 1)


class Pool:
    """Up to ``jobs`` worker processes that live for one fit (start-up paid once): :meth:`map`
    runs independent tasks on them, large arrays written once by :meth:`share` as ``.npy`` files that every
    worker maps read-only (:func:`shared`), not copied per task. Its workers stay in this process's
    group: killing a :class:`Worker` that runs a fit with a pool ends the pool's workers too.
    ``memory_limit``: bytes each worker may map (see :class:`Worker`)."""

    def __init__(self, jobs: int, memory_limit: float | None = None, preload=(), paths=()):
        self.jobs = max(1, int(jobs))
        self.paths = list(paths)
        self.memory_limit = memory_limit
        self.preload = list(preload)
        self.workers: list = []
        self.folder = None
        self._shared = 0

    def _start(self):
        if self.folder is None:
            self.folder = tempfile.mkdtemp(prefix="artdef-pool-")
        while len(self.workers) < self.jobs:
            self.workers.append(Worker(memory_limit=self.memory_limit, preload=self.preload,
                                       paths=self.paths, name="artdef-pool", own_group=False).start())

    def share(self, array) -> str:
        """Write ``array`` once for every worker; returns the path a task passes to :func:`shared`."""
        self._start()
        self._shared += 1
        path = os.path.join(self.folder, f"shared-{self._shared}.npy")
        np.save(path, np.ascontiguousarray(array), allow_pickle=False)
        return path

    def map(self, function: str, tasks: list, arrays: list | None = None, on_result=None) -> list:
        """``function`` on every task (a dict of JSON values; ``arrays[i]``: task i's own small
        arrays), spread over the workers; returns the ``(values, arrays)`` in task order.
        ``on_result(i, reply)`` is called here as each task's reply is taken (progress,
        cancelling: it may raise). A task that fails raises here: ``MemoryError`` for memory,
        else :class:`WorkerError`; the pool is then closed."""
        out = []
        for i, reply in enumerate(self.imap(function, tasks, arrays)):
            out.append(reply)
            if on_result is not None:
                on_result(i, reply)
        return out

    def imap(self, function: str, tasks: list, arrays: list | None = None):
        """:meth:`map` as a generator of the replies in task order, at most one task per worker
        ahead of the one it yields (a stream's memory stays that of a few replies)."""
        self._start()
        n = len(tasks)
        done = {}
        busy = {}                                   # worker index -> (task index, call)
        nxt = 0                                     # next task to hand out
        want = 0                                    # next reply to yield
        try:
            while want < n:
                for k, w in enumerate(self.workers):
                    if k not in busy and nxt < n and nxt - want < 2 * self.jobs:
                        busy[k] = (nxt, w.submit(function, arrays[nxt] if arrays else None, tasks[nxt]))
                        nxt += 1
                for k in [k for k, (i, call) in busy.items() if call.done]:
                    i, call = busy.pop(k)
                    done[i] = call.result()
                if want in done:
                    yield done.pop(want)
                    want += 1
                    continue
                if busy:
                    try:
                        self.workers[next(iter(busy))].process.wait(0.002)
                    except subprocess.TimeoutExpired:
                        pass
        except WorkerError as err:
            self.close()
            if err.kind == "memory":
                raise MemoryError(str(err)) from None
            raise
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for w in self.workers:
            w.close()
        self.workers = []
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


_CURRENT = []        # the pools of the fits running in this process, innermost last


class pooled:
    """``with pooled(jobs):`` — the stages of a fit inside the block may spread their independent
    work over :func:`current`'s pool of ``jobs`` processes (1: no pool, the serial path). The
    pool starts on first use and ends with the block."""

    def __init__(self, jobs: int, memory_limit: float | None = None):
        self.pool = Pool(jobs, memory_limit, preload=[f"{CORE}.api"]) if jobs > 1 else None

    def __enter__(self):
        _CURRENT.append(self.pool)
        return self.pool

    def __exit__(self, *exc):
        _CURRENT.pop()
        if self.pool is not None:
            self.pool.close()
        return False


def current() -> Pool | None:
    """The pool of the innermost :class:`pooled` block, or None (serial)."""
    return _CURRENT[-1] if _CURRENT else None


_MAPPED: dict = {}


def shared(path: str) -> np.ndarray:
    """In a pool's worker: the array :meth:`Pool.share` wrote at ``path``, mapped read-only once."""
    a = _MAPPED.get(path)
    if a is None:
        if len(_MAPPED) > 32:
            _MAPPED.clear()
        a = _MAPPED[path] = np.load(path, mmap_mode="r", allow_pickle=False)
    return a


# ----------------------------------------------------------------------------------------- child

class Reporter:
    """What a called function writes back: progress and log lines (read by :meth:`Call.poll`).
    ``folder``: the call's own folder (for files the function wants to leave there)."""

    def __init__(self, folder: str, parent: int | None = None):
        self.folder = folder
        self._f = open(os.path.join(folder, "messages.jsonl"), "a", encoding="utf-8")
        self._last = (None, 0.0)
        self._parent = parent

    def progress(self, stage: str, fraction: float) -> bool:
        """Record ``stage`` at ``fraction``; returns False (the parent cancels by killing), the
        shape of the core's progress callbacks. Ends this process if its parent is gone."""
        if self._parent is not None and os.getppid() != self._parent:
            os._exit(3)                       # orphaned: nobody waits for the result
        now = time.monotonic()
        if stage != self._last[0] or now - self._last[1] >= PROGRESS_EVERY or fraction >= 1.0:
            self._last = (stage, now)
            self._write({"progress": [str(stage), float(fraction)]})
        return False

    def log(self, text: str) -> None:
        self._write({"log": str(text)})

    def _write(self, obj) -> None:
        self._f.write(json.dumps(obj) + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def _limit_memory(limit: float | None) -> None:
    """RLIMIT_AS at what the process maps now plus ``limit`` bytes (Linux only)."""
    if not limit or not sys.platform.startswith("linux"):
        return
    import resource
    with open("/proc/self/status") as f:
        size = next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmSize:"))
    cap = int(size + limit)
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))


def _atomic_json(path: str, obj) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f)
    os.replace(tmp, path)


def _serve_call(folder: str, parent: int) -> None:
    """Run the call in ``folder`` and write its result (never raises for the function's errors)."""
    import importlib
    with open(os.path.join(folder, "call.json"), encoding="utf-8") as f:
        call = json.load(f)
    report = Reporter(folder, parent)
    try:
        # copy-on-write maps: read from the page cache, writable without touching the file
        arrays = {name: np.load(os.path.join(folder, f"in-{i}.npy"), mmap_mode="c", allow_pickle=False)
                  for i, name in enumerate(call["arrays"])}
        module, _, attr = call["function"].partition(":")
        fn = importlib.import_module(module)
        for part in attr.split("."):
            fn = getattr(fn, part)
        out = fn(arrays, call["params"], report)
        values, out_arrays = out if isinstance(out, tuple) else (out, {})
        names = list(out_arrays)
        for i, name in enumerate(names):
            tmp = os.path.join(folder, f"out-{i}.tmp.npy")
            np.save(tmp, np.asarray(out_arrays[name]), allow_pickle=False)
            os.replace(tmp, os.path.join(folder, f"out-{i}.npy"))
        reply = {"ok": True, "values": values or {}, "arrays": names}
    except MemoryError as exc:
        reply = {"ok": False, "memory": True, "type": "MemoryError", "message": str(exc)}
    except Exception as exc:
        import traceback
        line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        reply = {"ok": False, "type": type(exc).__name__, "message": line,
                 "traceback": traceback.format_exc()}
    finally:
        report.close()
    _atomic_json(os.path.join(folder, "result.json"), reply)


def main(argv=None) -> int:
    """The child: read the worker's settings, then serve the calls named on stdin until it ends."""
    import importlib
    folder = (argv or sys.argv[1:])[0]
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)      # the package's import set its own handlers
    with open(os.path.join(folder, "worker.json"), encoding="utf-8") as f:
        settings = json.load(f)
    for module in settings.get("preload", []):
        importlib.import_module(module)
    a = np.ones((256, 256))
    a @ a                        # OpenBLAS maps its buffers on the first product: before the limit
    _limit_memory(settings.get("memory_limit"))
    for line in sys.stdin:
        name = line.strip()
        if name:
            _serve_call(os.path.join(folder, os.path.basename(name)), settings.get("parent"))
    return 0


if __name__ == "__main__":
    sys.stdout.flush()
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)        # no interpreter teardown (the bpy module's can hang)
