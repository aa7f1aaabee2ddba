"""Walk one scan through ``to_laserscan`` / ``to_pointcloud2`` and count how often it climbs
back into a room it already left (issue 28, item 3: "at most 4 times each").

Run: ``.venv/bin/python bench/walk_rooms.py [--tree] [--moving]`` from the repository root.

A *room* is a top-level entry of ``converters/`` (a subpackage such as ``converters/slices/``
or a module such as ``converters/merger.py``) or of ``lidarscan/`` (a module). The walk traces
the Python call events (``sys.setprofile``) of one conversion on a warmed converter (imports,
numba and the per-info caches done by a first call) and prints two figures:

* ``calls`` (the issue's figure): the sequence of rooms of the called functions, consecutive
  repeats merged; a climb is a room that appears again after another room. It also counts a
  room calling one of its own functions after a lower room returned (the converter's own
  helper after the kernel, the converter cache taking its converter back).
* ``entries``: only calls that cross a room boundary count (the caller's room -- the nearest
  frame on the stack that lies in a room -- differs from the callee's); a room asking the same
  room again, with nothing asked of another room in between (what the callee asked of the
  rooms below it aside), is the same entry; a climb is an entry into a room that was entered
  before. This is the figure that
  says "visits each room once, going down": the converter asking ``lidarscan/scan.py`` for a
  channel, then ``lidarscan/stamps.py`` for a stamp, then ``lidarscan/scan.py`` again is one
  climb; the converter calling its own writer after the kernel is none.

``--tree`` prints the entries with their caller rooms; ``--moving``
walks ``to_laserscan`` with a moving mount (a ``TransformTrack``) as well. Nothing is timed.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: the tree walked: the working directory (run from the repository root), ahead of any
#: installed copy
ROOT = Path(os.getcwd()).resolve()
sys.path.insert(0, str(ROOT))

_ROOMS: dict[str, str | None] = {}


def room(filename: str) -> str | None:
    """The room of a source file, or None outside converters/ and lidarscan/."""
    found = _ROOMS.get(filename, "")
    if found != "":
        return found
    try:
        parts = Path(filename).resolve().relative_to(ROOT).parts
    except ValueError:
        parts = ()
    if not parts or parts[0] not in ("converters", "lidarscan"):
        found = None
    elif len(parts) == 2:
        found = parts[0] + "/" + parts[1]
    else:
        found = parts[0] + "/" + parts[1] + "/"
    _ROOMS[filename] = found
    return found


def _caller_room(frame: Any) -> str | None:
    f = frame.f_back
    while f is not None:
        r = room(f.f_code.co_filename)
        if r is not None:
            return r
        f = f.f_back
    return None


def walk(fn: Callable[[], Any]) -> dict[str, Any]:
    calls: list[str] = []
    entries: list[tuple[str | None, str]] = []

    def prof(frame: Any, event: str, arg: Any) -> None:
        if event != "call":
            return
        r = room(frame.f_code.co_filename)
        if r is None:
            return
        if not calls or calls[-1] != r:
            calls.append(r)
        caller = _caller_room(frame)
        if caller != r and (not entries or entries[-1] != (caller, r)):
            entries.append((caller, r))

    sys.setprofile(prof)
    try:
        fn()
    finally:
        sys.setprofile(None)
    seen: set[str] = set()
    call_climbs = 0
    for i, r in enumerate(calls):
        if r in seen and calls[i - 1] != r:
            call_climbs += 1
        seen.add(r)
    entered: set[str] = set()
    asked: dict[str | None, str] = {}      # caller room -> the room it asked last
    visits: list[tuple[str | None, str]] = []
    entry_climbs = 0
    for caller, r in entries:
        if asked.get(caller) == r:
            continue                       # asked again, the callee's own calls in between
        asked[caller] = r
        visits.append((caller, r))
        if r in entered:
            entry_climbs += 1
        entered.add(r)
    return {"calls": calls, "call_climbs": call_climbs, "entries": visits,
            "entry_climbs": entry_climbs, "rooms": len(set(calls))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tree", action="store_true", help="print the entries with callers")
    parser.add_argument("--moving", action="store_true", help="also a moving mount's slices")
    args = parser.parse_args()
    from converters.ouster import info_from_metadata

    import lidarscan as ls
    from converters import TransformTrack, to_laserscan, to_pointcloud2

    meta = ROOT / "converters" / "data" / "2_0_0_os1-992008000494-128_col_win_legacy.json"
    info = info_from_metadata(str(meta), stamp_ns=1)
    height, width = int(info.height), int(info.width)
    rng = np.random.default_rng(0)
    scan = ls.make_scan(info, {
        "range": rng.uniform(0.5, 30, (height, width)).astype(np.float32),
        "intensity": rng.integers(0, 1000, (height, width)).astype(np.uint16)}, 10,
        as_dataclass=True)
    cases: list[tuple[str, Callable[[], Any]]] = [
        ("to_laserscan", lambda: to_laserscan(scan, info, min_height=-0.2, max_height=0.5)),
        ("to_pointcloud2", lambda: to_pointcloud2(scan, info)),
    ]
    if args.moving:
        track = TransformTrack()
        for k, stamp in enumerate(range(-200_000_000, 300_000_000, 20_000_000)):
            pose = np.eye(4)
            pose[0, 3] = 0.01 * k
            track.add(stamp, pose)
        cases.append(("to_laserscan (moving)", lambda: to_laserscan(
            scan, info, min_height=-0.2, max_height=0.5, extrinsics=track,
            frame_id="odom")))
    for _, fn in cases:                              # warm: imports, numba, per-info caches
        fn()
    for name, fn in cases:
        found = walk(fn)
        print(f"{name}: {found['rooms']} rooms; climbs back: calls {found['call_climbs']}, "
              f"entries {found['entry_climbs']}")
        print("   calls:   " + " -> ".join(found["calls"]))
        print("   entries: " + " -> ".join(r for _, r in found["entries"]))
        if args.tree:
            for caller, r in found["entries"]:
                print(f"      {caller} => {r}")


if __name__ == "__main__":
    main()
