"""``lidarscan convert IN... OUT`` over many recordings: finding them, naming the outputs,
converting them in warm worker processes (``--jobs``) or on Dask (``--dask``), and deciding what
is already done (resumable runs).

Recordings (what one IN gives):

- a recording: an MCAP file, a rosbag2 folder, a ``.db3`` file, an Ouster ``.pcap``/``.osf``;
- a folder of recordings, searched recursively: a folder with ``metadata.yaml`` is one rosbag2
  recording (not searched further), and so is a folder whose recordings are only ``.db3`` files
  with no subfolder (split storage files whose ``metadata.yaml`` is missing); in any other
  folder every ``.mcap``, ``.db3``, ``.pcap`` and ``.osf`` file is a recording of its own (a
  folder of ``.mcap`` files is several recordings, not one merged bag). Names starting with
  ``.`` and the OUT folder are skipped;
- a glob (quoted, e.g. ``'runs/**/*.mcap'``), each match as above.

A run is a *fleet* run (OUT is a folder) when there are several INs, an IN is a glob or an IN is
a folder of recordings; a single recording keeps the single-file ``convert`` unchanged. Each
output is ``OUT/<path of the recording relative to its IN folder (or the glob's fixed part; a
file IN: its name)>`` with the suffix ``.mcap`` (a rosbag2 folder ``runs/a/bag`` -> ``OUT/a/bag.mcap``);
two recordings with the same output name are refused before anything is written.

Calibration: ``--calibration FILE`` / ``--metadata FILE`` given once applies to every recording.
Without it, a recording's own calibration is the first existing file of: ``<name>.yaml``,
``<name>.yml``, ``<name>.csv`` next to it (``<name>`` = the file's stem or the rosbag2 folder's
name), ``calibration.yaml|yml|csv`` inside its rosbag2 folder, ``calibration.yaml|yml|csv`` in
its folder; it is passed as ``--calibration`` only to recordings of raw packets. An Ouster
``.pcap``/``.osf`` takes ``<stem>.json`` next to it as ``--metadata``.

Done and up to date: after an output is renamed into place, a sidecar ``.<output name>.convert.json``
next to it records the input (path, total size, newest mtime in ns, file count), the digest of
the options that change the output (every ``convert`` option except ``--jobs``, ``--dask``,
``--force``, ``--threads``, ``--quiet``, ``--progress``) with the calibration file's path, size
and mtime and the lidarscan version, and the output's size. A later run skips a recording whose
sidecar matches all of them and whose output has the recorded size; one whose sidecar does not
match is converted again (said in the table: ``redone``); an output without a sidecar (made by
another command, or by an interrupted single-file ``convert``) is never overwritten: that
recording fails with the reason, unless ``--force`` (which redoes every recording).

Temporary files: ``convert`` writes ``.<output name>.<pid>.partial`` and renames it when the
recording is complete; a run removes the ones whose process is not running on this host (left by
a killed worker or a killed run) before it converts. Ctrl-C stops the workers (their partial
files are removed; no partial output under a final name) and exits 130 after the table. A worker
that dies (killed, out of memory) fails the recording it was converting after a second try; the
other recordings go on. Exit status: 0 every recording converted or up to date, 1 some failed or
had bad messages (each listed with its reason), 2 nothing was started (bad option or input),
130 interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from converters.edge.cli._argtypes import _positive_int
from converters.edge.cli._common import EXIT_BAD, EXIT_INTERRUPTED, EXIT_OK, _err

#: files that are recordings of their own in a folder without metadata.yaml
RECORDING_SUFFIXES = (".mcap", ".db3", ".pcap", ".osf")
#: a recording's own calibration file: these suffixes after its name or after "calibration"
CALIBRATION_SUFFIXES = (".yaml", ".yml", ".csv")
#: options that do not change an output's bytes (left out of the options digest)
RUN_OPTIONS = frozenset({"input", "output", "jobs", "dask", "force", "threads", "quiet",
                         "progress", "func", "command", "make_progress", "stats"})
#: tries of a recording whose worker died
TRIES = 2
#: environment of the Dask workers of a LocalCluster (and what to give remote ones, README).
#: Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 by default; any value set this way also
#: stops glibc's adaptive mmap threshold, so every numpy array above 128 KiB is mmap()ed and
#: unmapped again: the converter's system time more than doubled. These are the adaptive
#: scheme's upper values (bench/README.md, bench_fleet).
WORKER_ENV = {"MALLOC_TRIM_THRESHOLD_": str(64 << 20), "MALLOC_MMAP_THRESHOLD_": str(32 << 20)}


def add_options(parser: argparse.ArgumentParser) -> None:
    """``--jobs``, ``--dask``, ``--force`` of ``convert`` (fleet runs)."""
    parser.add_argument("--jobs", "-j", type=_positive_int, default=None, metavar="N",
                        help="several recordings: convert N at a time in warm worker processes "
                             "(default: all cores); every output is the one converting that "
                             "recording alone gives")
    parser.add_argument("--dask", nargs="?", const="", default=None, metavar="ADDRESS",
                        help="several recordings: convert them on Dask distributed: a local "
                             "cluster of --jobs workers, or the scheduler at ADDRESS "
                             "(tcp://host:8786; default $DASK_SCHEDULER_ADDRESS) whose workers "
                             "see the same paths; needs the [dask] extra. Give it after OUT or "
                             "as --dask=ADDRESS")
    parser.add_argument("--force", action="store_true",
                        help="several recordings: convert every one again, also those whose "
                             "output is up to date, and overwrite outputs this command did not "
                             "write")


# ------------------------------------------------------------------------------ recordings

@dataclass(frozen=True)
class Recording:
    """One recording of a fleet run.

    Attributes:
        path: the recording (a file, or a rosbag2 folder).
        rel: its output path relative to OUT (suffix ``.mcap``).
    """

    path: Path
    rel: Path


def _has_magic(text: str) -> bool:
    return any(c in text for c in "*?[")


def is_bag_folder(folder: Path) -> bool:
    """A folder that is one rosbag2 recording: ``metadata.yaml``, or ``.db3`` files and no
    other recording or subfolder."""
    if (folder / "metadata.yaml").is_file():
        return True
    db3 = other = False
    for entry in folder.iterdir():
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            other = True
        elif entry.suffix.lower() == ".db3":
            db3 = True
        elif entry.suffix.lower() in RECORDING_SUFFIXES:
            other = True
    return db3 and not other


def _walk(root: Path, skip: Path | None) -> Iterator[Path]:
    """The recordings under ``root`` (a folder of recordings), in name order."""
    for entry in sorted(root.iterdir()):
        if entry.name.startswith(".") or (skip is not None and entry.resolve() == skip):
            continue
        if entry.is_dir():
            if is_bag_folder(entry):
                yield entry
            else:
                yield from _walk(entry, skip)
        elif entry.suffix.lower() in RECORDING_SUFFIXES and entry.is_file():
            yield entry


def is_fleet(inputs: Sequence[str]) -> bool:
    """Whether the INs make a fleet run (see the module docstring)."""
    if len(inputs) != 1:
        return True
    path = Path(inputs[0])
    if not path.exists():
        return _has_magic(inputs[0])
    return path.is_dir() and not is_bag_folder(path) and next(_walk(path, None), None) is not None


def find_recordings(inputs: Sequence[str], out: Path) -> list[Recording]:
    """Every recording of ``inputs`` with its output path relative to ``out``.

    Raises:
        FileNotFoundError: an IN that does not exist or a glob that matches nothing.
        ConfigError: two recordings would write the same output.
    """
    import glob

    from lidarscan.errors import ConfigError

    skip = out.resolve()
    found: list[Recording] = []
    for name in inputs:
        path = Path(name)
        if path.exists():
            roots = [(path, path if path.is_dir() and not is_bag_folder(path) else path.parent)]
        elif _has_magic(name):
            parts = Path(name).parts
            fixed = Path(*parts[:next(i for i, p in enumerate(parts) if _has_magic(p))] or ".")
            matches = [Path(m) for m in sorted(glob.glob(name, recursive=True))]
            roots = [(m, fixed) for m in matches
                     if m.is_dir() or m.suffix.lower() in RECORDING_SUFFIXES]
            if not roots:
                raise FileNotFoundError(f"IN {name}: the pattern matches no recording")
        else:
            raise FileNotFoundError(f"IN {name}: no such file or directory")
        for match, base in roots:
            if match.is_dir() and not is_bag_folder(match):
                items = list(_walk(match, skip))
                if not items and path.exists():
                    raise FileNotFoundError(f"IN {match}: a folder without recordings "
                                            f"({', '.join(RECORDING_SUFFIXES)} files or rosbag2 "
                                            "folders)")
            else:
                items = [match]
            for item in items:
                rel = item.relative_to(base) if base != item else Path(item.name)
                rel = rel.with_name(item.name if item.is_dir() else item.stem).with_suffix("")
                found.append(Recording(item, Path(f"{rel}.mcap")))
    unique: dict[Path, Recording] = {}
    outputs: dict[Path, Recording] = {}
    for rec in found:
        if rec.path.resolve() in unique:
            continue
        unique[rec.path.resolve()] = rec
        other = outputs.setdefault(rec.rel, rec)
        if other is not rec:
            raise ConfigError("OUT", str(out / rec.rel), f"one output per recording ({other.path} "
                              f"and {rec.path} would both write it): convert them separately")
    return list(unique.values())


def companion(path: Path) -> Path | None:
    """A recording's own calibration (``.pcap``/``.osf``: metadata JSON) found next to it, or
    None (rule in the module docstring)."""
    if path.is_file() and path.suffix.lower() in (".pcap", ".osf"):
        candidates = [path.with_suffix(".json")]
    else:
        stem = path.name if path.is_dir() else path.stem
        candidates = [path.parent / f"{stem}{s}" for s in CALIBRATION_SUFFIXES]
        if path.is_dir():
            candidates += [path / f"calibration{s}" for s in CALIBRATION_SUFFIXES]
        candidates += [path.parent / f"calibration{s}" for s in CALIBRATION_SUFFIXES]
    return next((c for c in candidates if c.is_file()), None)


def signature(path: Path) -> dict[str, int]:
    """Total size, newest mtime (ns) and file count of a recording (a file or a folder)."""
    files = [path] if path.is_file() else [f for f in sorted(path.rglob("*")) if f.is_file()]
    stats = [f.stat() for f in files]
    return {"size": sum(s.st_size for s in stats),
            "mtime_ns": max((s.st_mtime_ns for s in stats), default=0), "files": len(stats)}


# ------------------------------------------------------------------------------------ jobs

@dataclass(frozen=True)
class Job:
    """One recording to convert: what a worker needs (picklable)."""

    index: int
    source: str
    output: str
    rel: str
    size: int
    options: dict[str, Any]
    companion: str | None = None
    sidecar: dict[str, Any] = field(default_factory=dict)


@dataclass
class Result:
    """How one recording went. ``status``: ``ok``, ``redone``, ``bad`` (converted, some
    messages bad), ``skipped`` (up to date), ``failed``, ``interrupted``."""

    index: int
    status: str
    reason: str = ""
    lines: list[str] = field(default_factory=list)
    read: int = 0
    written: int = 0
    seconds: float = 0.0
    out_size: int = 0


def sidecar_path(output: Path) -> Path:
    return output.with_name(f".{output.name}.convert.json")


def options_digest(options: dict[str, Any], calibration: Path | None) -> str:
    """sha256 (16 hex digits) of the options that change an output, the calibration file and
    the lidarscan version."""
    try:
        from importlib.metadata import version
        lidarscan_version = version("lidarscan")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        lidarscan_version = "?"
    cal = None
    if calibration is not None:
        st = calibration.stat()
        cal = [str(calibration.resolve()), st.st_size, st.st_mtime_ns]
    text = json.dumps({"options": {k: v for k, v in sorted(options.items())
                                   if k not in RUN_OPTIONS},
                       "calibration": cal, "version": lidarscan_version},
                      sort_keys=True, default=repr)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this host (a zombie, e.g. a killed worker nobody
    reaped, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat.rpartition(")")[2].split()[:1] != ["Z"]


def stale_partials(output: Path) -> list[Path]:
    """The temporary files of ``output`` whose process is not running (on this host)."""
    out = []
    for tmp in output.parent.glob(f".{output.name}.*.partial") if output.parent.is_dir() else ():
        pid = tmp.name[:-len(".partial")].rpartition(".")[2]
        if not pid.isdigit() or not _pid_alive(int(pid)):
            out.append(tmp)
    return out


def state(job: Job, force: bool) -> tuple[str, str, dict[str, Any]]:
    """``("skip", why)``, ``("convert", "")``, ``("redo", why)`` or ``("refuse", why)`` for a
    job whose output may exist (module docstring), with the output's sidecar record as read
    (``{}`` when none was read)."""
    output = Path(job.output)
    if not output.exists():
        return "convert", "", {}
    if force:
        return "redo", "--force", {}
    if output.is_dir():
        return "refuse", f"OUT {output} is a directory", {}
    try:
        done = json.loads(sidecar_path(output).read_text())
    except (OSError, ValueError):
        return "refuse", (f"{output} exists and was not written by a run of this command (no "
                          f"{sidecar_path(output).name}): not overwritten; --force to convert "
                          "again"), {}
    for key, why in (("input", "another input"), ("input_signature", "input changed"),
                     ("options", "options changed")):
        if done.get(key) != job.sidecar.get(key):
            return "redo", why, done
    if done.get("output_size") != output.stat().st_size:
        return "redo", "output changed", done
    return "skip", done.get("status", "ok"), done


# ---------------------------------------------------------------------------- the worker

_EVENTS: Any = None  # the run's event queue in a local worker process (None on Dask)


def _init_worker(events: Any) -> None:
    """A local worker: Ctrl-C is the parent's (it stops the workers); the converter imported
    once (warm)."""
    global _EVENTS
    _EVENTS = events
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import importlib

    for name in ("converters.sources.bags", "converters.edge.cli.convert", "lidarscan.mcap"):
        importlib.import_module(name)


class _QueueProgress:
    """The :class:`converters.edge.cli._common.Progress` interface of a worker: sends the fraction
    done of its recording to the parent at most 5 times a second."""

    def __init__(self, events: Any, index: int, total: int, label: str, **_: Any) -> None:
        self.events, self.index, self.total, self.label = events, index, max(int(total), 1), label
        self._last = 0.0

    def update(self, done: int, extra: str = "", *, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last >= 0.2:
            self._last = now
            self.events.put(("progress", self.index, min(max(done / self.total, 0.0), 1.0)))

    def close(self) -> None:
        return


def _packet_recording(source: str) -> bool:
    """Whether ``convert`` decodes packets of the recording (so its companion file is their
    calibration): the test ``convert`` uses (an IMU packet topic alone is not lidar packets)."""
    from converters.edge.cli._common import _open_input
    from converters.sources.bags import is_packet_topic

    return any(is_packet_topic(t, k) for t, k in _open_input(source, "IN").topics().items())


def convert_job(job: Job) -> Result:
    """Convert one recording in this process, as ``lidarscan convert IN OUT`` with the run's
    options; its messages are returned (not printed); on success the sidecar is written."""
    from converters.edge.cli.convert import cmd_convert
    from lidarscan.errors import LidarScanError

    start = time.perf_counter()
    if _EVENTS is not None:
        _EVENTS.put(("start", job.index, os.getpid()))
    args = argparse.Namespace(**job.options)
    args.input, args.output, args.quiet, args.progress = job.source, job.output, True, False
    args.stats = {}
    if _EVENTS is not None:
        args.make_progress = lambda *a, **k: _QueueProgress(_EVENTS, job.index, *a, **k)
    buffer = io.StringIO()
    status, reason = "failed", ""
    try:
        with contextlib.redirect_stderr(buffer):
            if job.companion and Path(job.source).suffix.lower() in (".pcap", ".osf"):
                args.metadata = job.companion
            elif job.companion and _packet_recording(job.source):
                args.calibration = job.companion
            code = cmd_convert(args)
        status = {EXIT_OK: "ok", EXIT_BAD: "bad"}.get(code, "failed")
        if status == "bad":
            reason = f"{args.stats.get('bad', 0)} bad message(s) or damaged part(s) skipped"
    except LidarScanError as err:
        reason = str(err)
    except ModuleNotFoundError as err:
        from lidarscan._install import missing_module_hint
        reason = missing_module_hint(err, "lidarscan convert")
    except (OSError, ImportError) as err:
        reason = str(err)
    except Exception as err:  # noqa: BLE001 - one recording's bug must not stop the others
        reason = f"internal error {type(err).__name__}: {err}"
    result = Result(job.index, status, reason, buffer.getvalue().splitlines(),
                    args.stats.get("read", 0), args.stats.get("written", 0),
                    time.perf_counter() - start)
    if status in ("ok", "bad"):
        output = Path(job.output)
        result.out_size = output.stat().st_size
        _write_sidecar(output, {**job.sidecar, "status": status, "reason": reason,
                                "output_size": result.out_size, "read": result.read,
                                "written": result.written})
    return result


def _write_sidecar(output: Path, record: dict[str, Any]) -> None:
    path = sidecar_path(output)
    tmp = output.with_name(f".{output.name}.convert.json.{os.getpid()}.partial")
    tmp.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- runners

Event = Callable[[str, int, Any], None]


def run_local(jobs: Sequence[Job], workers: int, on_event: Event) -> Iterator[Result]:
    """The results of ``jobs`` converted by ``workers`` warm processes (spawned, each
    importing the converter once), as they finish. A job whose worker died is tried again
    (:data:`TRIES` in all). Ctrl-C: the workers are stopped and KeyboardInterrupt raised."""
    import multiprocessing
    import queue as queue_module
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    context = multiprocessing.get_context("spawn")
    events = context.Queue()
    pending = {job.index: job for job in jobs}
    tries: dict[int, int] = {}

    def drain() -> None:
        while True:
            try:
                kind, index, value = events.get_nowait()
            except queue_module.Empty:
                return
            if kind == "start":
                started[index] = value
            on_event(kind, index, value)

    while pending:
        started: dict[int, int] = {}
        pool = ProcessPoolExecutor(min(workers, len(pending)), mp_context=context,
                                   initializer=_init_worker, initargs=(events,))
        broken = False
        try:
            # largest first: the last recordings to finish are small ones; the workers start
            # here, ignoring Ctrl-C from their first instruction (it is this process's)
            with _sigint_ignored():
                futures = {pool.submit(convert_job, job): job for job in
                           sorted(pending.values(), key=lambda j: (-j.size, j.index))}
            waiting = set(futures)
            while waiting:
                done, waiting = wait(waiting, timeout=0.1, return_when=FIRST_COMPLETED)
                drain()
                for future in done:
                    try:
                        result = future.result()
                    except BrokenProcessPool:
                        broken = True
                        continue
                    pending.pop(result.index, None)
                    started.pop(result.index, None)
                    yield result
                if broken:
                    break
        except BaseException:
            _stop(pool)
            raise
        finally:
            if broken:
                _stop(pool)
            pool.shutdown(wait=True, cancel_futures=True)
        if broken:
            drain()
            for index, pid in started.items():
                if index not in pending:
                    continue
                output = Path(pending[index].output)
                output.with_name(f".{output.name}.{pid}.partial").unlink(missing_ok=True)
                tries[index] = tries.get(index, 0) + 1
                if tries[index] >= TRIES:
                    pending.pop(index)
                    yield Result(index, "failed", f"its worker process died {TRIES} times "
                                 "(killed, or out of memory)")


def _stop(pool: Any) -> None:
    """Terminate the pool's worker processes (Python 3.11 has no public call for it)."""
    for process in list(getattr(pool, "_processes", {}).values()):
        with contextlib.suppress(Exception):
            process.terminate()


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored meanwhile (in the main thread; elsewhere nothing changes)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def run_dask(jobs: Sequence[Job], workers: int, address: str, on_event: Event
             ) -> Iterator[Result]:
    """The results of ``jobs`` converted on Dask distributed (futures, ``as_completed``): the
    scheduler at ``address`` (or $DASK_SCHEDULER_ADDRESS), else a LocalCluster of ``workers``
    single-threaded worker processes with :data:`WORKER_ENV`."""
    import logging

    import dask
    from distributed import Client, LocalCluster, as_completed

    address = address or os.environ.get("DASK_SCHEDULER_ADDRESS", "")
    with contextlib.ExitStack() as stack:
        if address:
            client = stack.enter_context(Client(address, timeout="20s"))
        else:
            environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
            environ.update(WORKER_ENV)
            stack.enter_context(dask.config.set({"distributed.nanny.pre-spawn-environ":
                                                 environ}))
            # the workers ignore Ctrl-C (inherited): it is this process's, which cancels the
            # work and closes the cluster (a worker of its own ended in a traceback)
            with _sigint_ignored():
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                       processes=True, dashboard_address=None,
                                       silence_logs=logging.ERROR)
            stack.enter_context(cluster)
            client = stack.enter_context(Client(cluster))
        token = f"{os.getpid()}-{time.time_ns()}"
        largest_first = sorted(jobs, key=lambda j: (-j.size, j.index))
        futures = [client.submit(convert_job, job, key=f"lidarscan-convert-{token}-{job.index}",
                                 pure=False, retries=TRIES - 1)
                   for job in largest_first]
        index = {future.key: job.index for future, job in zip(futures, largest_first)}
        try:
            for future in as_completed(futures):
                try:
                    result = future.result()
                except Exception as err:  # noqa: BLE001 - a worker lost, a pickling error...
                    result = Result(index[future.key], "failed", f"dask: {err}")
                on_event("progress", result.index, 1.0)
                yield result
        except BaseException:
            client.cancel(futures)
            raise


# ------------------------------------------------------------------------------ the command

def cmd_convert_many(args: argparse.Namespace) -> int:
    """``lidarscan convert IN... OUT``: one recording -> :func:`converters.edge.cli.convert.cmd_convert`
    (unchanged); several -> :func:`run_fleet`."""
    from converters.edge.cli.convert import cmd_convert

    inputs = list(args.input)
    if args.dask and not _is_address(args.dask) and Path(args.dask).exists():
        inputs.insert(0, args.dask)   # `--dask IN... OUT`: argparse took IN as the address
        args.dask = ""
    if not is_fleet(inputs):
        args.input = inputs[0]
        return cmd_convert(args)
    return run_fleet(args, inputs)


def _is_address(text: str) -> bool:
    import re
    return re.match(r"^[a-z+]+://|^[\w.-]+:\d+$", text) is not None


def plan(args: argparse.Namespace, inputs: Sequence[str]) -> list[Job]:
    """One job per recording of ``inputs`` into the folder OUT (all checked before anything is
    written)."""
    from converters.edge.cli.convert_checks import check_option_files
    from lidarscan.errors import ConfigError

    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise ConfigError("OUT", str(out), "a folder for the outputs of several recordings "
                          "(it is a file)")
    if not out.exists() and out.suffix.lower() in RECORDING_SUFFIXES:
        raise ConfigError("OUT", str(out), f"a folder for the outputs of several recordings "
                          f"(IN {' '.join(inputs)} is {len(inputs)} or more recordings; a "
                          f"folder of {out.suffix} files without metadata.yaml is not one bag)")
    check_option_files(args)
    recordings = find_recordings(inputs, out)
    options = {k: v for k, v in vars(args).items() if k not in ("func", "input", "output")}
    if (args.jobs or os.cpu_count() or 1) > 1 or args.dask is not None:
        options["threads"] = 1   # the jobs fill the cores; same bytes for every --threads
    jobs = []
    for k, rec in enumerate(recordings):
        found = None if args.calibration or args.metadata else companion(rec.path)
        given = args.metadata if rec.path.suffix.lower() in (".pcap", ".osf") \
            else args.calibration
        cal = Path(given) if given else found
        sig = signature(rec.path)
        jobs.append(Job(k, str(rec.path), str(out / rec.rel), rec.rel.as_posix(), sig["size"],
                        options, str(found) if found else None,
                        {"input": str(rec.path.resolve()), "input_signature": sig,
                         "options": options_digest(options, cal)}))
    return jobs


def run_fleet(args: argparse.Namespace, inputs: Sequence[str]) -> int:
    """Convert every recording of ``inputs`` into the folder OUT (module docstring)."""
    from converters.edge.cli.progress import FleetProgress, table

    jobs = plan(args, inputs)
    if args.dask is not None:
        try:
            import distributed  # noqa: F401
        except ImportError as err:
            raise ModuleNotFoundError("--dask needs Dask distributed", name="distributed") \
                from err
    results: dict[int, Result] = {}
    todo: list[Job] = []
    notes: dict[int, str] = {}
    redo: set[int] = set()
    for job in jobs:
        for tmp in stale_partials(Path(job.output)):
            tmp.unlink(missing_ok=True)
            notes[job.index] = f"removed {tmp.name} (left by a killed run)"
        decision, why, done = state(job, args.force)
        if decision == "skip":   # as converted then; with its bad messages then (exit 1)
            bad = why == "bad"
            results[job.index] = Result(
                job.index, "skipped-bad" if bad else "skipped",
                "up to date" + (f"; {done.get('reason')}" if bad else ""), [],
                done.get("read", 0), done.get("written", 0), 0.0, done.get("output_size", 0))
        elif decision == "refuse":
            results[job.index] = Result(job.index, "failed", why)
        else:
            if decision == "redo":
                redo.add(job.index)
                notes[job.index] = "; ".join(filter(None, (why, notes.get(job.index))))
            Path(job.output).parent.mkdir(parents=True, exist_ok=True)
            todo.append(job)
    workers = max(1, min(args.jobs or os.cpu_count() or 1, len(todo) or 1))
    progress = FleetProgress({j.index: j.size for j in todo}, len(jobs),
                             enabled=not args.quiet)
    by_index = {job.index: job for job in jobs}
    interrupted = False

    def on_event(kind: str, index: int, value: Any) -> None:
        if kind == "progress":
            progress.advance(index, value)

    started = time.perf_counter()
    try:
        runner = iter(()) if not todo else run_dask(todo, workers, args.dask, on_event) \
            if args.dask is not None else run_local(todo, workers, on_event)
        for result in runner:
            if result.status == "ok" and result.index in redo:
                result.status = "redone"
            results[result.index] = result
            progress.finish(result.index)
            rel = by_index[result.index].rel
            for line in result.lines:
                progress.note(f"{rel}: {line}")
    except KeyboardInterrupt:
        interrupted = True
    finally:
        progress.close()
    for job in todo:
        if job.index not in results:
            for tmp in stale_partials(Path(job.output)):
                tmp.unlink(missing_ok=True)
            results[job.index] = Result(job.index, "interrupted", "not converted (Ctrl-C)")
    rows = [(by_index[i], results[i], notes.get(i, "")) for i in sorted(results)]
    failed = [r for _, r, _ in rows if r.status in ("failed", "bad", "skipped-bad")]
    for line in table(rows, time.perf_counter() - started, quiet=args.quiet):
        _err(line)
    if interrupted:
        return EXIT_INTERRUPTED
    return EXIT_BAD if failed else EXIT_OK

