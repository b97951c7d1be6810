"""Load generators: a busy companion computer on demand, for ``bench/safety_load.py`` and the
tests that check the bridge beside one (:mod:`loadgen.load`, and :mod:`loadgen.supervisor` that
runs in each load's own process).

Test and bench support, outside the ``esc-bridge`` package and its wheel: pytest finds it from
the repository's root (``pythonpath`` in pyproject.toml), the bench scripts from beside them
(``bench/_common.py``).
"""
