"""The compiled kernels of the live path (Cython); everything else is in pyproject.toml."""

from Cython.Build import cythonize
from setuptools import Extension, setup

# No -ffast-math and no FMA contraction: the kernels must give the same floating-point bits as the
# numpy batch paths they are tested against.
FLAGS = ["-O2", "-ffp-contract=off", "-mpopcnt"]

setup(
    ext_modules=cythonize(
        [
            Extension(name, [name.replace(".", "/") + ".pyx"], extra_compile_args=FLAGS)
            for name in (
                "daemon._dtw",
                "daemon._automaton",
                "daemon._features",
                "daemon._live",
                "replay._kinematics",
            )
        ],
        compiler_directives={"language_level": 3},
    )
)
