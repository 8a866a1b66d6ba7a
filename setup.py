"""Build the compiled kernels of contact_viz.patch (everything else is in pyproject.toml)."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(
    ext_modules=cythonize(
        [Extension("contact_viz.geometry._patch_kernels", ["src/contact_viz/geometry/_patch_kernels.pyx"], extra_compile_args=["-O3"])],
        language_level=3,
    )
)
