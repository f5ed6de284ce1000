"""Build of the compiled parts of core (the metadata is in pyproject.toml)."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(
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
    )
)
