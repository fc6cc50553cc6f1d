"""Where the test suite's time goes to XLA compilation: every compile, by program
and by test file.

As a pytest plugin it logs each backend compile (JAX's ``jax_log_compiles``
messages: program name and seconds) with the test that caused it, one JSON file
per worker; as a script it sums them beside the per-file test times of the run's
``--durations=0`` list:

    PYTHONPATH=experiments python -m pytest -q -p compile_profile --durations=0 > run.log
    python experiments/compile_profile.py run.log

The files go to ``$JDEM_COMPILE_PROFILE_DIR`` (default /tmp/jdem-compile-profile);
a new pytest run replaces them.
"""
from __future__ import annotations

import collections
import json
import logging
import os
import pathlib
import re
import sys

OUT = pathlib.Path(os.environ.get("JDEM_COMPILE_PROFILE_DIR", "/tmp/jdem-compile-profile"))
_MESSAGE = re.compile(r"Finished XLA compilation of (.*) in ([0-9.e+-]+) sec")
_records: list = []
_current = {"test": None}


class _CompileLog(logging.Handler):
    def emit(self, record):
        m = _MESSAGE.search(record.getMessage())
        if m:
            _records.append((_current["test"], m.group(1)[:80], float(m.group(2))))


# ----------------------------------------------------------------------------- pytest hooks
def pytest_configure(config):
    import jax

    jax.config.update("jax_log_compiles", True)
    logger = logging.getLogger("jax")
    logger.addHandler(_CompileLog())
    logger.setLevel(logging.DEBUG)
    if not hasattr(config, "workerinput"):       # the controlling process: a fresh folder
        OUT.mkdir(parents=True, exist_ok=True)
        for old in OUT.glob("compiles_*.json"):
            old.unlink()


def pytest_runtest_logstart(nodeid, location):
    _current["test"] = nodeid


def pytest_unconfigure(config):
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"compiles_{worker}.json").write_text(json.dumps(_records))


# ----------------------------------------------------------------------------- report
def report(log: pathlib.Path, most: int = 15) -> list[str]:
    """Lines: compiles and seconds by program, then test time and compile time by file."""
    records = [r for f in sorted(OUT.glob("compiles_*.json")) for r in json.loads(f.read_text())]
    by_program = collections.defaultdict(lambda: [0, 0.0])
    compile_by_file = collections.defaultdict(float)
    for test, program, seconds in records:
        by_program[program][0] += 1
        by_program[program][1] += seconds
        compile_by_file[(test or "outside a test").split("::")[0]] += seconds
    test_by_file = collections.defaultdict(float)
    for line in log.read_text().splitlines():
        m = re.match(r"\s*([0-9.]+)s (call|setup|teardown)\s+(\S+)", line)
        if m:
            test_by_file[m.group(3).split("::")[0]] += float(m.group(1))
    total = sum(s for _, _, s in records)
    lines = [f"{len(records)} compiles, {total:.0f} s of compilation; test time (all workers) "
             f"{sum(test_by_file.values()):.0f} s", "", "| program | compiles | seconds |",
             "|---|---|---|"]
    lines += [f"| {p} | {c} | {s:.1f} |" for p, (c, s) in
              sorted(by_program.items(), key=lambda x: -x[1][1])[:most]]
    lines += ["", "| test file | test time [s] | of it compiling [s] |", "|---|---|---|"]
    lines += [f"| {f} | {t:.1f} | {compile_by_file.get(f, 0.0):.1f} |" for f, t in
              sorted(test_by_file.items(), key=lambda x: -x[1])[:most]]
    return lines


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    print("\n".join(report(pathlib.Path(sys.argv[1]))))
