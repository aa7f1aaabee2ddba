"""A large synthetic rosbag2 .db3 for the memory benchmark: the rows of a small real bag
repeated (timestamps shifted by one period each time) until the file has the asked size."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path


def grow_db3(seed: Path, target: Path, size: int) -> Path:
    """Copy ``seed`` (a rosbag2 .db3) to ``target`` and repeat its messages until ``target`` is
    at least ``size`` bytes; the message count in the topics is whatever the rows are (this
    reader counts the rows). Returns ``target``."""
    shutil.copy(seed, target)
    con = sqlite3.connect(target)
    rows = con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp").fetchall()
    first, last = rows[0][1], rows[-1][1]
    period = (last - first) + (last - first) // max(len(rows) - 1, 1)
    seed_bytes = sum(len(r[2]) for r in rows)
    repeats = max(1, -(-size // seed_bytes) - 1)
    for k in range(1, repeats + 1):
        con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                        [(t, s + k * period, d) for t, s, d in rows])
        if k % 16 == 0:
            con.commit()
    con.commit()
    con.close()
    return target
