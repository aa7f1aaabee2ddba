"""Every compiled piece of the converters, behind one selection function: :func:`select`.

Each algorithm has one readable reference in numpy (the spec, and the test oracle); the
compiled backends below are optional accelerations that must give the same bits (or stay within
the ulps documented by their module) and are kept only where a bench/ figure shows they pay
(bench/README.md).

==========  ==============================  =======================  ============================
backend     where                           needs                    used by
==========  ==============================  =======================  ============================
C cloud     ``_cloudkernel.c`` via          a C compiler at          LidarScan -> PointCloud2
            :mod:`.cloud` (ctypes)          ``pip install``          (x, y, z, validity, one
                                                                     channel field)
C velodyne  ``_velokernel.c`` via           a C compiler at          Velodyne packets -> channel
            :mod:`.velodyne` (ctypes)       ``pip install``          views and header checks
                                                                     (converters.sources.velodyne)
C slices    ``_slicekernel.c`` via          a C compiler at          slices, row-ordered case
            :mod:`.slices` (ctypes)         ``pip install``;         (full circle at the column
                                            AVX-512 to be chosen     resolution, upright mount)
                                            by ``"auto"`` when
                                            numba is installed
C cloud     ``_cloudslicekernel.c`` via     a C compiler at          unstructured PointCloud2 ->
slices      :mod:`.cloud_slices` (ctypes)   ``pip install``          slices
                                                                     (converters.slices.cloud;
                                                                     AVX2 build chosen at run
                                                                     time)
numba       :mod:`.slices_numba`            ``pip install numba``    slices (row-ordered,
                                            (extra ``fast``)         bin-ordered and general
                                                                     kernels) and the merger
numba       :mod:`.hesai`                   ``pip install numba``    Hesai packets -> grids
                                            (extra ``fast``)         (converters.sources.hesai.decoder)
numba       ``lidarscan.codec._compiled``   ``pip install numba``    residual coding of
            (in the core: the codec's       (extra ``fast``)         lidarscan.codec (its
            default coder;                                           default ``coder="auto"``;
            ``_compiled_v3``: version 3's                            ``"codec"`` here returns it)
            fit and prediction)
numpy       the converters themselves       --                       everything (the reference)
==========  ==============================  =======================  ============================

Switches, read by :mod:`lidarscan._backends` (the lowest layer, so that the core's codec honours
them too) and asked here (at the first use of a backend in the process):
``LIDARSCAN_NO_KERNEL`` set to anything but "" / "0" disables the C kernels (the Velodyne one
is re-checked at each ``select``, the others at their first use);
``LIDARSCAN_NUMBA=0`` disables numba; ``LIDARSCAN_CLOUD_SIMD=0`` / ``LIDARSCAN_VELODYNE_SIMD=0``
(read when :mod:`.cloud` / :mod:`.velodyne` are loaded; their ``SIMD`` attributes) force the
PointCloud2 / Velodyne kernels' portable code where the CPU has AVX-512 / AVX2. Per object, ``kernel=`` (PointCloud2: None = when built,
False = numpy, True = required) and ``backend=`` (slices and merger: ``"auto"``, ``"numba"``,
``"numpy"``, ``"c"``) choose among what is enabled. ``"c"`` never compiles at run time: the C
kernels (built at install) where they apply, else numpy; the nodes run it while numba's cache
lacks their kernels (:mod:`converters.warmup`).

Kernels take native-byte-order arrays only: byte order is converted once at the message
boundary (:func:`lidarscan.scan.channel` with ``native=True``).

Warm-up: numba compiles a kernel at its first call (seconds) or loads it from its on-disk cache
(a large part of a second), and the C kernels load at their first use. :mod:`converters.warmup`
(above this package: it drives the converters) does both for a configuration before the first
message; the nodes call it before they subscribe, and ``lidarscan-warmup`` (``python -m
converters.warmup``, run by ``make install``) fills the cache for every specialisation. This
package imports nothing of ``converters`` outside itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from lidarscan._backends import c_enabled, numba_enabled
from lidarscan.errors import ConfigError

__all__ = ["Backends", "c_enabled", "numba_enabled", "select"]


@dataclass(frozen=True)
class Backends:
    """The compiled pieces one object will use (None / False: use numpy).

    Attributes:
        c: the C kernel's entry points (:class:`.cloud.Kernels` for "cloud"; True for
            "slices", whose plans bind :func:`.slices.library` themselves; ``lcs_slices`` of
            :mod:`.cloud_slices` for "cloud_slices"; the ctypes library of :mod:`.velodyne` for
            "velodyne"), or None.
        numba: the compiled numba kernels (:func:`.slices_numba.kernels`), or None.
    """

    c: Any = None
    numba: Any = None


def select(task: str, *, backend: str = "auto", kernel: bool | None = None) -> Backends:
    """The backends of one converter object.

    Args:
        task: ``"cloud"`` (PointCloud2, chosen by ``kernel``), ``"slices"``, ``"merger"`` or
            ``"cloud_slices"`` (chosen by ``backend``), ``"hesai"`` (packet decoding: numba
            when enabled), ``"velodyne"`` (packet decoding: the C kernel, ``c``, when built and
            enabled), ``"codec"`` (the compiled :class:`lidarscan.codec.ResidualCoder`,
            ``numba``, when enabled: what ``compress_scan`` / ``decompress_scan`` run by
            default, :func:`lidarscan.codec.residual_coder`).
        backend: ``"auto"``: the fastest enabled (slices: the C kernel where its vector path
            runs or numba is missing, else numba, else numpy; cloud slices: the C kernel, else
            numpy); ``"numba"``: numba only (an error when it is missing, and for the cloud
            slices, which have no numba kernel); ``"numpy"``: the reference; ``"c"``: nothing
            compiled at run time (slices and cloud slices: the C kernel when built and enabled,
            whatever its vector path; merger: numpy).
        kernel: PointCloud2 only: None = the C kernel when built and enabled, False = numpy,
            True = the C kernel or an error.

    Raises:
        ConfigError: a bad choice, or a required backend that is not available.
    """
    if task == "cloud":
        if kernel not in (None, True, False):
            raise ConfigError("kernel", kernel, "None, True or False")
        from converters._kernels import cloud
        fns = cloud.kernel() if kernel is not False else None
        if kernel and fns is None:
            raise ConfigError("kernel", kernel, "None or False: the compiled kernel is not "
                              "available (not built, or LIDARSCAN_NO_KERNEL is set)")
        return Backends(c=fns)
    if task == "hesai":
        from converters._kernels import hesai
        return Backends(numba=hesai.kernel() if numba_enabled() else None)
    if task == "velodyne":
        from converters._kernels import velodyne
        return Backends(c=velodyne.library())
    if task == "codec":
        from lidarscan.codec import NUMPY, residual_coder
        coder = residual_coder("auto")
        return Backends(numba=None if coder is NUMPY else coder)
    if task not in ("slices", "merger", "cloud_slices"):
        raise ConfigError("task", task, "'cloud', 'slices', 'merger', 'cloud_slices', 'hesai', "
                          "'velodyne' or 'codec'")
    if backend not in ("auto", "numba", "numpy", "c"):
        raise ConfigError("backend", backend, "'auto', 'numba', 'numpy' or 'c'")
    if task == "cloud_slices":
        if backend == "numba":
            raise ConfigError("backend", backend, "'auto' (the compiled C kernel when it is "
                              "built) or 'numpy': the cloud slices have no numba kernel")
        from converters._kernels import cloud_slices
        return Backends(c=cloud_slices.library() if backend in ("auto", "c") else None)
    numba = None
    if backend == "c":
        if task == "merger":
            return Backends()
        from converters._kernels import slices
        return Backends(c=slices.available() or None)
    if backend != "numpy":
        from converters._kernels import slices_numba
        numba = slices_numba.kernels()
    if backend == "numba" and numba is None:
        raise ConfigError("backend", backend, "numba installed (pip install numba)")
    c = False
    if task == "slices" and backend == "auto":
        from converters._kernels import slices
        # the C kernel's scalar path (no AVX-512) is slower than numba's kernel
        c = slices.available() and (slices.vectorised() or numba is None)
    return Backends(c=c or None, numba=numba)

