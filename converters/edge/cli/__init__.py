"""The ``lidarscan`` command line (console script ``lidarscan = converters.edge.cli:main``; also
``python -m converters.edge.cli``).

Commands::

    lidarscan --version
    lidarscan demo [--out DIR] [--frames N] [--no-images]
    lidarscan info REC [--metadata JSON]
    lidarscan convert REC OUT.mcap|OUT/ [--pointcloud2] [--preset P | --fields x,y,z,...]
                                   [--slice NAME:ZMIN:ZMAX[:holes[:KEY=VALUE]...]]...
                                   [--frame F] [--extrinsics ...]
                                   [--merge] [--merge-topic TOPIC]... [--calibration FILE]
                                   [--cut-angle DEG] [--replace] [--keep-packets] [--progress]
                                   [--compress] [--chunk-compression C] [--zstd-level N] [-q]
                                   [--start TIME] [--end TIME] [--topics T1,T2]
                                   [--rename-topic OLD=NEW]...
    lidarscan convert IN... OUTDIR [--jobs N | --dask [ADDRESS]] [--force] [options as above]
    lidarscan view REC --out DIR [--index K]

(each command's ``--help`` ends with examples: :mod:`._examples`). ``convert`` writes an MCAP
file, or a rosbag2 folder (MCAP storage + ``metadata.yaml``) when OUT ends in ``/`` or is an
existing empty folder (:mod:`.convert_checks`); ``--start``/``--end``/``--topics`` select what is
read and ``--rename-topic`` names the output topics (:mod:`.convert_filters`).

REC is an MCAP file, a rosbag2 directory (``metadata.yaml`` + ``.db3`` or ``.mcap`` storage) or a
single rosbag2 ``.db3`` file; ``convert`` also takes an Ouster ``.pcap``/``.pcapng`` (decoded
here, with ``--metadata``) or ``.osf`` (through ouster-sdk). What a path is
is told from its contents and said in every error about it.

Exit status: 0 success; 1 the run finished but some messages or parts of the input were bad
(each one reported on stderr: index, topic, stamp and reason, or for a damaged part of the file
its offset and time range) or, for ``info``, problems were found; 2 usage error or fatal error
(missing, empty or unreadable input, input of the wrong kind, an invalid option value, an option
that does not fit the recording, an output topic that clashes with an input topic): nothing is
written; 130 interrupted by Ctrl-C (``convert`` still closes its output, which is a valid MCAP of
everything written so far: the first Ctrl-C only asks it to stop between two messages,
:mod:`._interrupt`).

``convert`` writes OUT under a temporary name next to it and renames it only when the run ends
(also with bad messages, exit 1): a failed run never leaves a partial or empty OUT.

Only this package prints and exits; everything it calls raises. One module per command
(:mod:`.demo`, :mod:`.info`, :mod:`.convert` with :mod:`.convert_pipeline` and
:mod:`.convert_inputs`, many recordings in :mod:`.fleet` with :mod:`.progress`, :mod:`.view`), shared parts in :mod:`._common` (exit codes, progress,
inputs) and the argparse parser in :mod:`._parser`.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from converters.edge.cli._common import (
    EXIT_BAD,
    EXIT_FATAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    Progress,
    _err,
)
from converters.edge.cli._parser import build_parser
from converters.edge.cli.convert import parse_slice
from converters.edge.cli.convert_pipeline import ConvertReport

__all__ = ["build_parser", "main", "parse_slice", "ConvertReport", "Progress", "EXIT_OK",
           "EXIT_BAD", "EXIT_FATAL", "EXIT_INTERRUPTED"]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (see the module docstring)."""
    from lidarscan.errors import LidarScanError

    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "preset", "") and getattr(args, "fields", ()):
        parser.error("--preset and --fields: give one of them (a preset fixes the fields)")
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    except BrokenPipeError:   # `lidarscan info REC | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no flush error at exit
        return EXIT_OK
    except LidarScanError as err:
        _err(f"lidarscan {args.command}: error: {err}")
        return EXIT_FATAL
    except ModuleNotFoundError as err:    # an extra or a message package not installed
        from lidarscan._install import missing_module_hint
        _err(f"lidarscan {args.command}: error: "
             f"{missing_module_hint(err, f'lidarscan {args.command}')}")
        return EXIT_FATAL
    except (OSError, ImportError) as err:
        _err(f"lidarscan {args.command}: error: {err}")
        return EXIT_FATAL
