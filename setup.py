"""Build of the optional compiled CityGML geometry walk (`db/citygml/_walk.pyx`, Cython over
lxml's libxml2 nodes). Everything else is in pyproject.toml.

The extension is optional: when Cython, a C compiler or the Python headers are missing, the
install goes on without it and `db.citygml.building_read` uses its Python walk (same rows, slower
import). `make install` (pip install -e) builds it; CI installs `build-essential python3-dev`.
"""

from setuptools import setup

try:
    import lxml
    from Cython.Build import cythonize
except ImportError:  # no Cython or lxml in the build environment: the Python walk is used
    ext_modules = []
else:
    from setuptools import Extension

    ext_modules = cythonize(
        [
            Extension(
                "db.citygml._walk",
                ["db/citygml/_walk.pyx"],
                include_dirs=lxml.get_include(),
                optional=True,
            )
        ],
        compiler_directives={"language_level": "3"},
        quiet=True,
    )

setup(ext_modules=ext_modules)
