"""The worker process (artdef_addon.procs): a normal call, and each way a call ends without a result."""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from artdef_addon import procs

pytestmark = pytest.mark.core

HERE = os.path.dirname(os.path.abspath(__file__))


def worker(**kw):
    return procs.Worker(paths=[HERE], **kw)


def until(call, predicate, seconds=60):
    """Poll ``call`` until a message satisfies ``predicate``; returns the messages seen."""
    seen, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        new = call.poll()
        seen += new
        if any(predicate(m) for m in new) or call.done:
            return seen
        try:
            call.worker.process.wait(0.02)
        except subprocess.TimeoutExpired:
            pass
    raise AssertionError(f"no such message within {seconds} s: {seen}")


def gone_within(pid, seconds):
    """Whether process ``pid`` is gone or a zombie (dead, not yet reaped) within ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rpartition(")")[2].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
    return False


def test_a_call_runs_in_another_process_and_returns_its_arrays_and_messages():
    a = np.arange(12.0).reshape(4, 3)
    b = np.array([[1, 2, 3]], dtype=np.int32)
    messages = []
    w = worker()
    with w:
        call = w.submit("worker_calls:echo", {"a": a, "b": b}, {"links": 3, "name": "rod"})
        values, arrays = call.wait(messages.append)
        folder = w.folder
        assert os.path.isdir(folder)
        # a second call on the same process (start-up paid once)
        again, _ = w.submit("worker_calls:echo", {"a": a}).wait()
    assert values["pid"] != os.getpid() and again["pid"] == values["pid"]
    assert values["params"] == {"links": 3, "name": "rod"}
    assert values["writable"]                       # copy-on-write maps: the function may write
    assert np.array_equal(arrays["a"], 2 * a) and arrays["b"].dtype == np.int32
    assert np.array_equal(arrays["b"], 2 * b)
    assert [m["progress"] for m in messages if "progress" in m] == [["step 0", 0.0], ["step 1", 0.5],
                                                                     ["step 2", 1.0]]
    assert {"log": "got ['a', 'b']"} in messages
    assert not os.path.exists(folder)               # temporaries removed


def test_an_exception_in_the_function_is_one_line_and_the_worker_serves_on():
    with worker() as w:
        with pytest.raises(procs.WorkerError) as info:
            w.submit("worker_calls:fail").wait()
        assert info.value.kind == "error" and info.value.type_name == "ValueError"
        assert str(info.value) == "the scan has no faces"
        values, _ = w.submit("worker_calls:echo", {"a": np.zeros(2)}).wait()
        assert values["pid"] == w.pid


@pytest.mark.skipif(os.name != "posix", reason="signals")
def test_a_crash_names_the_signal():
    w = worker()
    with w:
        with pytest.raises(procs.WorkerError) as info:
            w.submit("worker_calls:abort").wait()
        folder = w.folder
    assert info.value.kind == "crashed" and "SIGABRT" in str(info.value)
    assert "\n" not in str(info.value)
    assert not os.path.exists(folder)


def test_an_exit_without_a_result_names_the_exit_code():
    with worker() as w, pytest.raises(procs.WorkerError) as info:
        w.submit("worker_calls:leave").wait()
    assert info.value.kind == "crashed" and "exited with code 3" in str(info.value)


@pytest.mark.skipif(os.name != "posix", reason="signals")
def test_a_worker_killed_from_outside_mid_call():
    with worker() as w:
        call = w.submit("worker_calls:block")
        until(call, lambda m: "progress" in m)
        os.kill(w.pid, signal.SIGKILL)
        with pytest.raises(procs.WorkerError) as info:
            call.wait()
    assert info.value.kind == "killed" and "SIGKILL" in str(info.value)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="process groups, /proc")
def test_kill_ends_the_worker_and_what_it_started_within_a_second():
    w = worker()
    with w:
        call = w.submit("worker_calls:block")
        seen = until(call, lambda m: "progress" in m)
        grandchild = int(next(m["log"] for m in seen if "log" in m))
        t0 = time.monotonic()
        w.kill()
        with pytest.raises(procs.WorkerError) as info:
            call.result()
        took = time.monotonic() - t0
        folder = w.folder
    assert info.value.kind == "cancelled" and took < 1.0
    assert not w.alive()
    assert gone_within(grandchild, 1.0)
    assert not os.path.exists(folder)


def test_a_call_past_its_timeout_is_stopped():
    with worker() as w:
        t0 = time.monotonic()
        with pytest.raises(procs.WorkerError) as info:
            w.submit("worker_calls:block", timeout=0.5).wait()
        assert time.monotonic() - t0 < 0.5 + procs.KILL_WAIT + 0.5
        assert not w.alive()
    assert info.value.kind == "timeout" and "0.5 s" in str(info.value)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_AS is enforced on Linux")
def test_a_call_over_the_memory_limit_is_one_line_and_the_parent_is_unharmed():
    limit = 256 * 2**20
    with worker(memory_limit=limit) as w:
        with pytest.raises(procs.WorkerError) as info:
            w.submit("worker_calls:allocate", params={"bytes": 4 * limit}).wait()
        assert not w.alive()              # a worker after a failed allocation is not kept
    assert info.value.kind == "memory" and "256 MB" in str(info.value)
    # within the limit the same call succeeds
    values, _ = procs.run("worker_calls:allocate", params={"bytes": limit // 4}, paths=[HERE],
                          memory_limit=limit)
    assert values["sum"] == limit // 32


def test_object_arrays_are_refused_before_the_child_sees_them():
    with worker() as w, pytest.raises(ValueError, match="Python objects"):
        w.submit("worker_calls:echo", {"a": np.array([{}, None], dtype=object)})


def test_a_pool_spreads_tasks_over_its_processes_on_one_shared_array():
    a = np.random.default_rng(5).random((1000, 7))
    with procs.Pool(2, paths=[HERE]) as pool:
        path = pool.share(a)
        tasks = [{"a": path, "rows": [s, s + 100]} for s in range(0, 1000, 100)]
        ends = []
        out = pool.map("worker_calls:row_sums", tasks, on_result=lambda i, r: ends.append(i))
        pids = {v["pid"] for v, _ in out}
        assert len(pool.workers) == 2 and pids <= {w.pid for w in pool.workers}
        again = pool.map("worker_calls:row_sums", tasks[:2])
        assert {v["pid"] for v, _ in again} <= pids          # the same processes: started once
        with pytest.raises(procs.WorkerError, match="negative row"):
            pool.map("worker_calls:row_sums", [{"a": path, "rows": [-1, 0]}])
        assert pool.workers == [] and pool.folder is None      # a failed map closes the pool
    assert sorted(ends) == list(range(10))
    assert np.array_equal(np.concatenate([r["sums"] for _, r in out]), a.sum(axis=1))
    assert os.getpid() not in pids
