"""``lidarscan demo``: simulate, convert, record and draw (:func:`converters.edge.demo.run.run_demo`)."""

from __future__ import annotations

import argparse

from converters.edge.cli._common import EXIT_OK, Progress, _err


def cmd_demo(args: argparse.Namespace) -> int:
    import importlib.util

    from converters.edge.demo.run import run_demo
    from lidarscan._install import missing_module_hint

    images = not args.no_images
    if images and importlib.util.find_spec("matplotlib") is None:   # a plain `pip install`
        images = False
        _err(f"note: no PNG views: {missing_module_hint('matplotlib', 'lidarscan demo')}")
    progress = Progress(args.frames, "simulating")
    try:
        result = run_demo(args.out, args.frames, images=images,
                          noise_m=args.noise, progress=lambda d, t: progress.update(d, f"{d}/{t}"))
    finally:
        progress.close()
    print(result.summary())
    return EXIT_OK
