"""Build of the compiled parts of core (the metadata is in pyproject.toml)."""

import os

from Cython.Build import cythonize
from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


class ParallelBuildExt(build_ext):
    """Compiles the extensions side by side (each is one large C file): half the time of
    building the venv on a 2-core machine goes to gcc otherwise."""

    def finalize_options(self) -> None:
        super().finalize_options()
        if self.parallel is None:
            self.parallel = os.cpu_count() or 1


setup(
    cmdclass={"build_ext": ParallelBuildExt},
    ext_modules=cythonize(
        [
            Extension("core._blobs", ["core/_blobs.pyx"], extra_compile_args=["-O3"]),
            # -ffp-contract=off: no fused multiply-add, so that the loops give numpy's bits.
            Extension(
                "core._geometry",
                ["core/_geometry.pyx"],
                extra_compile_args=["-O3", "-ffp-contract=off"],
            ),
            Extension(
                "core._tracks",
                ["core/_tracks.pyx"],
                extra_compile_args=["-O3", "-ffp-contract=off"],
            ),
        ],
        compiler_directives={"language_level": "3"},
    ),
)
