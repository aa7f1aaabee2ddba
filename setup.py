"""Build of the optional compiled kernels; all other metadata lives in pyproject.toml.

``converters/_kernels/_cloudkernel.c`` speeds up LidarScan -> PointCloud2,
``converters/_kernels/_slicekernel.c`` LidarScan -> LaserScan slices,
``converters/_kernels/_cloudslicekernel.c`` unstructured PointCloud2 -> slices and
``converters/_kernels/_velokernel.c`` Velodyne packets -> LidarScan (the table of backends is
the header of converters/_kernels/__init__.py). All are optional: without a C compiler the
install still succeeds and the numba / numpy paths are used.
(A setup.py because ``[tool.setuptools] ext-modules`` needs setuptools >= 74.1.)
"""

from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.command.build_py import build_py


class BuildExt(build_ext):  # type: ignore[misc]
    """No fused multiply-add (the table form must round like numpy, and every CPU-specific
    variant of the factored form must give the same bits); no floating-point traps assumed,
    so branch-free selects vectorise."""

    def build_extensions(self) -> None:
        if self.compiler.compiler_type == "msvc":
            args = ["/O2", "/fp:precise"]          # MSVC contracts only with /fp:contract
        else:
            args = ["-O3", "-ffp-contract=off", "-fno-fast-math", "-fno-trapping-math"]
        for ext in self.extensions:
            ext.extra_compile_args = list(ext.extra_compile_args or []) + args
        super().build_extensions()


class BuildPy(build_py):  # type: ignore[misc]
    """Also copy ``msgs/msg/*.msg`` (the definitions of lidarscan_msgs) into the built package as
    ``lidarscan/_msgs/``: an installed lidarscan (no checkout next to it, no interface package
    built) still has the MCAP schemas and CDR layouts of its own messages
    (``lidarscan/msgdef.py`` looks there after the source tree)."""

    def run(self) -> None:
        super().run()
        target = Path(self.build_lib) / "lidarscan" / "_msgs"
        self.mkpath(str(target))
        sources = Path(__file__).resolve().parent / "msgs" / "msg"
        for source in sorted(sources.glob("*.msg")):
            self.copy_file(str(source), str(target / source.name))


setup(
    ext_modules=[Extension("converters._kernels._cloudkernel",
                           ["converters/_kernels/_cloudkernel.c"], optional=True),
                 Extension("converters._kernels._slicekernel",
                           ["converters/_kernels/_slicekernel.c"], optional=True),
                 Extension("converters._kernels._cloudslicekernel",
                           ["converters/_kernels/_cloudslicekernel.c"], optional=True),
                 Extension("converters._kernels._velokernel",
                           ["converters/_kernels/_velokernel.c"], optional=True)],
    cmdclass={"build_ext": BuildExt, "build_py": BuildPy},
)
