"""The compiled kernels of the live path (Cython); everything else is in pyproject.toml."""

from Cython.Build import cythonize
from setuptools import Extension, setup

# No -ffast-math and no FMA contraction: the kernels must give the same floating-point bits as the
# numpy batch paths they are tested against.
FLAGS = ["-O2", "-ffp-contract=off", "-mpopcnt"]
# The feature program's instructions and forward kinematics' steps run over a block of frames
# (Bytecode.run_many, FrameKinematics.joints_many): vectorised loops of IEEE adds, multiplies,
# divisions and square roots give the bits the scalar ones give.
VECTORISED = ["-ftree-vectorize", "-fvect-cost-model=dynamic"]
EXTRA = {"daemon._features": VECTORISED, "replay._kinematics": VECTORISED}

setup(
    ext_modules=cythonize(
        [
            Extension(name, [name.replace(".", "/") + ".pyx"], extra_compile_args=FLAGS + EXTRA.get(name, []))
            for name in (
                "daemon._dtw",
                "daemon._automaton",
                "daemon._features",
                "daemon._live",
                "replay._kinematics",
                "protocols._route",
            )
        ],
        compiler_directives={"language_level": 3},
    )
)
