"""Build of the optional compiled parts of the import: the CityGML geometry walk
(`db/citygml/_walk.pyx`, Cython over lxml's libxml2 nodes) and the float texts of its rows
(`db/_fmt.pyx`, Ryu). Everything else is in pyproject.toml.

The extensions are optional: when Cython, a C compiler or the Python headers are missing, the
install goes on without them and the Python code is used (same rows, slower import;
`db/compiled.py`). `make install` (pip install -e) builds them in place; CI installs
`build-essential python3-dev` (.ci/system-deps.sh), the image gcc (Dockerfile).
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
            ),
            # repr() of floats for the import's rows through Ryu (db/_ryu, vendored)
            Extension("db._fmt", ["db/_fmt.pyx"], include_dirs=["db/_ryu"], optional=True),
        ],
        compiler_directives={"language_level": "3"},
        quiet=True,
    )

setup(ext_modules=ext_modules)
