"""Test oracles: the plain (numpy or slower numba) implementations that groomtool's fast kernels
replaced and reproduce, bit for bit or to round-off, and that only the tests (and benches) use.

The tests import them as ``reference.<module>`` (pytest puts tests/ on sys.path); a bench adds
tests/ to sys.path first.  One module per groomtool package: ``reference.contact``,
``reference.fit``, ``reference.rods``, ``reference.solvers``, ``reference.equilibrium`` (stability and
inversion), ``reference.stability`` (the finite-difference contact load Hessian).
"""
