#!/usr/bin/env python
"""Mutation testing of the physics modules: does the fast test suite notice a
wrong operator, comparison or sign?

    python experiments/mutation.py                       # 6 mutants per module
    python experiments/mutation.py --per-module 20 --modules bond contact
    python experiments/mutation.py --list                # the mutants, not run
    python experiments/mutation.py --all --modules bond  # every site of a module
    python experiments/mutation.py --all --modules bond --rerun-survivors  # after new tests
    python experiments/mutation.py --report              # mutation.md from the outcomes so far

For each module, every candidate mutation site is collected from its syntax
tree: an arithmetic operator swapped (+ <-> -, * <-> /), a comparison flipped
(< <-> <=, > <-> >=, == <-> !=), a unary minus dropped, ``jnp.minimum`` <->
``jnp.maximum``.  ``--per-module`` of them are drawn at random (``--seed``),
and each is written into a scratch copy of the package (``--work``, a git
worktree of HEAD) and the module's unit-test files are run there (``pytest -x``,
one process).  A mutant is *killed* when a test fails (or the run errors or
times out), *survived* otherwise.  The original sources are never touched.

Each outcome is appended to ``experiments/results/mutation/results.jsonl`` as
soon as it is known, keyed by the module's code hash (:func:`code_hash`: the
syntax tree without docstrings, line and column positions included, so an edit
of comments or docstrings that moves no code keeps the outcomes and any other
edit starts the module afresh): a run that is interrupted, or a later run with
more sites, continues where the last stopped (sites already run on the same
code are skipped).  Outcomes recorded before the code hash was kept carry only
the hash of the raw source; that is mapped to a code hash through the module's
versions in git history.  ``equivalent.json`` in the same folder names the mutants judged
equivalent (key ``module | mutation | col C | code line``, value the reason); they are
left out of the score.  ``mutation.md`` (score per module, each mutant with its
line and outcome) is written from both after every mutant.  Slow (20-60 s per
mutant on 2 cores, mostly compilation): a study run on request, not part of the
test suite.
"""
from __future__ import annotations

import argparse
import ast
import datetime
import hashlib
import json
import pathlib
import random
import shutil
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "mutation"

#: module -> the unit-test files that should catch its mutants
TESTS = {
    "bond": ["tests/test_bond_unit.py", "tests/test_bond_unequal.py", "tests/test_bond_section.py"],
    "contact": ["tests/test_contact_laws.py", "tests/test_contact_spin.py"],
    "damping": ["tests/test_damping_timestep.py"],
    "timestep": ["tests/test_damping_timestep.py", "tests/test_input_errors.py"],
    "kinematics": ["tests/test_contact_spin.py", "tests/test_bond_unequal.py"],
    "walls": ["tests/test_guard.py", "tests/test_contact_laws.py", "tests/test_contact_spin.py",
              "tests/test_engine.py"],
    "neighbors": ["tests/test_neighbors.py", "tests/test_history_reorder.py"],
    "integrate": ["tests/test_integrate.py", "tests/test_engine.py", "tests/test_guard.py"],
}

_BINOPS = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult}
_CMPS = {ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq,
         ast.NotEq: ast.Eq}
_CALLS = {"minimum": "maximum", "maximum": "minimum"}


def _docstring_lines(tree) -> set:
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                lines.update(range(first.lineno, first.end_lineno + 1))
    return lines


def sites(source: str) -> list:
    """Every mutation site: (kind, line, col, description)."""
    tree = ast.parse(source)
    skip = _docstring_lines(tree)
    out = []
    for node in ast.walk(tree):
        line = getattr(node, "lineno", None)
        if line is None or line in skip:
            continue
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            out.append(("binop", line, node.col_offset,
                        f"{type(node.op).__name__} -> {_BINOPS[type(node.op)].__name__}"))
        elif isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in _CMPS:
            out.append(("compare", line, node.col_offset,
                        f"{type(node.ops[0]).__name__} -> {_CMPS[type(node.ops[0])].__name__}"))
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            out.append(("neg", line, node.col_offset, "drop unary minus"))
        elif isinstance(node, ast.Attribute) and node.attr in _CALLS:
            out.append(("call", line, node.col_offset, f"{node.attr} -> {_CALLS[node.attr]}"))
    # nested nodes can share a position and an operator (a * b * c): the mutation
    # hits the first, so such a site is one mutant
    return sorted(set(out), key=lambda s: (s[1], s[2], s[0], s[3]))


class _Mutate(ast.NodeTransformer):
    def __init__(self, site):
        super().__init__()
        self.kind, self.line, self.col, desc = site
        self.before = desc.split(" -> ")[0]     # nested nodes may share a position
        self.done = False

    def _hit(self, node):
        return (not self.done and getattr(node, "lineno", None) == self.line
                and node.col_offset == self.col)

    def visit_BinOp(self, node):
        if self.kind == "binop" and self._hit(node) and type(node.op).__name__ == self.before:
            node.op, self.done = _BINOPS[type(node.op)](), True
        return self.generic_visit(node)

    def visit_Compare(self, node):
        if self.kind == "compare" and self._hit(node) and \
                type(node.ops[0]).__name__ == self.before:
            node.ops, self.done = [_CMPS[type(node.ops[0])]()], True
        return self.generic_visit(node)

    def visit_UnaryOp(self, node):
        if self.kind == "neg" and self._hit(node) and isinstance(node.op, ast.USub):
            self.done = True
            return self.generic_visit(node.operand)
        return self.generic_visit(node)

    def visit_Attribute(self, node):
        if self.kind == "call" and self._hit(node) and node.attr == self.before:
            node.attr, self.done = _CALLS[node.attr], True
        return self.generic_visit(node)


def mutate(source: str, site) -> str:
    tree = ast.parse(source)
    m = _Mutate(site)
    tree = m.visit(tree)
    if not m.done:
        raise RuntimeError(f"site not found: {site}")
    return ast.unparse(ast.fix_missing_locations(tree))


def _worktree(work: pathlib.Path):
    if work.exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(work)],
                       capture_output=True)
        shutil.rmtree(work, ignore_errors=True)
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(work), "HEAD"],
                   check=True, capture_output=True)


def run_tests(work: pathlib.Path, files, timeout) -> tuple[str, float]:
    # no bytecode: two mutants of a file can have the same size and modification
    # second, and Python would then run the previous mutant's cached bytecode
    for cache in (work / "jdem").rglob("__pycache__"):
        shutil.rmtree(cache, ignore_errors=True)
    env = dict(__import__("os").environ, PYTHONPATH=str(work), JAX_PLATFORMS="cpu",
               PYTHONDONTWRITEBYTECODE="1")
    t0 = time.time()
    try:
        r = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-o", "addopts=",
                            "-m", "not slow", "-p", "no:cacheprovider", *files], cwd=work,
                           env=env, capture_output=True, text=True, timeout=timeout)
        outcome = "survived" if r.returncode == 0 else "killed"
    except subprocess.TimeoutExpired:
        outcome = "killed (timeout)"
    return outcome, time.time() - t0


def source_hash(src: str) -> str:
    """Hash of the raw source text (the key of outcomes recorded before
    :func:`code_hash`)."""
    return hashlib.sha256(src.encode()).hexdigest()[:16]


def code_hash(src: str) -> str:
    """Hash of what the module executes: its syntax tree with every docstring
    removed, node positions included (a mutant's line and column stay valid)."""
    tree = ast.parse(src)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str)):
            node.body = body[1:]
    return hashlib.sha256(ast.dump(tree, include_attributes=True).encode()).hexdigest()[:16]


_HISTORY: dict = {}


def code_hash_of_record(r) -> str | None:
    """The code hash an outcome was recorded on: stored, or (older records) found
    from the raw-source hash among the module's versions in git history."""
    if "code_sha" in r:
        return r["code_sha"]
    mod = r["module"]
    if mod not in _HISTORY:
        _HISTORY[mod] = {}
        path = f"jdem/{mod}.py"
        log = subprocess.run(["git", "-C", str(ROOT), "log", "--format=%H", "--", path],
                             capture_output=True, text=True).stdout.split()
        for commit in log:
            shown = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:{path}"],
                                   capture_output=True, text=True)
            if shown.returncode == 0:
                _HISTORY[mod][source_hash(shown.stdout)] = code_hash(shown.stdout)
    return _HISTORY[mod].get(r["source_sha"])


def equivalence_key(r) -> str:
    return f"{r['module']} | {r['mutation']} | col {r['col']} | {r['code']}"


def load_results(out: pathlib.Path) -> list:
    """The latest outcome of each mutant (module, line, col, mutation, source) in
    ``results.jsonl``, in the order first run: a mutant re-run after new tests
    (``--rerun-survivors``) keeps its place and takes its new outcome."""
    path = out / "results.jsonl"
    if not path.exists():
        return []
    latest = {}
    for x in path.read_text().splitlines():
        if x.strip():
            r = json.loads(x)
            latest[(r["module"], r["line"], r["col"], r["mutation"],
                    code_hash_of_record(r) or r["source_sha"])] = r
    return list(latest.values())


def write_report(out: pathlib.Path, hashes: dict, n_sites: dict, cmd: str):
    """mutation.md from results.jsonl (current sources only) and equivalent.json."""
    eq_path = out / "equivalent.json"
    equivalent = json.loads(eq_path.read_text()) if eq_path.exists() else {}
    recorded = load_results(out)
    results = [r for r in recorded if hashes.get(r["module"]) == code_hash_of_record(r)]
    unmatched = sum(code_hash_of_record(r) is None for r in recorded)
    md = ["# Mutation testing of the physics modules", "",
          f"Last run {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, `{cmd}`, "
          f"2-core CPU. A mutant is killed when the module's unit tests (`pytest -x`, not "
          f"slow) fail; mutants named in `equivalent.json` are left out of the score. "
          f"Outcomes accumulate in `results.jsonl` across runs on the same code (docstrings and comments aside).", "",
          "| module | sites | run | killed | equivalent | survived | score of non-equivalent |",
          "|---|---|---|---|---|---|---|"]
    for mod in sorted(n_sites):
        rows = [r for r in results if r["module"] == mod]
        if not rows:
            md.append(f"| {mod} | {n_sites[mod]} | 0 | | | | not run on the current code |")
            continue
        k = sum(r["outcome"].startswith("killed") for r in rows)
        e = sum((not r["outcome"].startswith("killed")) and equivalence_key(r) in equivalent
                for r in rows)
        sv = len(rows) - k - e
        md.append(f"| {mod} | {n_sites.get(mod, '?')} | {len(rows)} | {k} | {e} | {sv} | "
                  f"{100 * k / max(k + sv, 1):.0f} % |")
    stale = len(recorded) - len(results) - unmatched
    md += ["", f"{stale} recorded outcomes belong to earlier versions of the modules and are "
           f"not counted."]
    if unmatched:   # records older than the code hash, with no git history to map them
        md += [f"{unmatched} recorded outcomes could not be matched to any version of their "
               f"module (no git history here) and are not counted."]
    md += ["", "| module | line | mutation | outcome | note | code |", "|---|---|---|---|---|---|"]
    for r in results:
        note = equivalent.get(equivalence_key(r), "") if not r["outcome"].startswith("killed") \
            else ""
        md.append(f"| {r['module']} | {r['line']} | {r['mutation']} | {r['outcome']} | {note} | "
                  f"`{r['code'][:80].replace('|', '/')}` |")
    (out / "mutation.md").write_text("\n".join(md) + "\n")
    return md


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modules", nargs="+", default=list(TESTS))
    ap.add_argument("--per-module", type=int, default=6)
    ap.add_argument("--all", action="store_true", help="every site of each module")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--work", type=pathlib.Path, default=pathlib.Path("/tmp/jdem-mutation"))
    ap.add_argument("--rerun-survivors", action="store_true",
                    help="run again the survivors not judged equivalent (after new tests)")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--report", action="store_true",
                    help="only write mutation.md from the outcomes recorded so far")
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    a = ap.parse_args(argv)
    rng = random.Random(a.seed)
    plan, hashes, n_sites = {}, {}, {}
    for mod in TESTS:             # every module's current source, for the report
        src = (ROOT / "jdem" / f"{mod}.py").read_text()
        hashes[mod] = code_hash(src)
        all_sites = sites(src)
        n_sites[mod] = len(all_sites)
        if mod in a.modules:
            chosen = all_sites if a.all else rng.sample(all_sites,
                                                        min(a.per_module, len(all_sites)))
            plan[mod] = (len(all_sites), chosen)
    if a.report:
        print("\n".join(write_report(a.out, hashes, n_sites, "python experiments/mutation.py "
                                     "--report")[:11 + len(TESTS)]))
        return
    if a.list:
        for mod, (n, chosen) in plan.items():
            print(f"{mod}: {n} sites; " + "; ".join(f"line {s[1]}: {s[3]}" for s in chosen))
        return
    a.out.mkdir(parents=True, exist_ok=True)
    cmd = "python experiments/mutation.py " + " ".join(sys.argv[1:] if argv is None else argv)
    eq_path = a.out / "equivalent.json"
    equivalent = json.loads(eq_path.read_text()) if eq_path.exists() else {}
    done = {(r["module"], r["line"], r["col"], r["mutation"]) for r in load_results(a.out)
            if hashes.get(r["module"]) == code_hash_of_record(r)
            and not (a.rerun_survivors and r["outcome"] == "survived"
                     and equivalence_key(r) not in equivalent)}
    _worktree(a.work)
    try:
        for mod, (n, chosen) in plan.items():
            todo = [st for st in chosen if (mod, st[1], st[2], st[3]) not in done]
            print(f"{mod}: {len(chosen) - len(todo)} of {len(chosen)} already run", flush=True)
            if not todo:
                continue
            target = a.work / "jdem" / f"{mod}.py"
            original = target.read_text()
            base, t_base = run_tests(a.work, TESTS[mod], a.timeout)
            if base != "survived":
                raise RuntimeError(f"the tests of {mod} fail without a mutant")
            for site in todo:
                target.write_text(mutate(original, site))
                outcome, t = run_tests(a.work, TESTS[mod], a.timeout)
                target.write_text(original)
                line = original.splitlines()[site[1] - 1].strip()
                r = dict(module=mod, line=site[1], col=site[2], mutation=site[3], code=line,
                         outcome=outcome, seconds=round(t, 1), source_sha=source_hash(original),
                         code_sha=hashes[mod])
                with open(a.out / "results.jsonl", "a") as f:
                    f.write(json.dumps(r) + "\n")
                write_report(a.out, hashes, n_sites, cmd)
                print(f"{mod}:{site[1]} {site[3]:24s} {outcome:16s} {t:5.0f} s  {line[:70]}",
                      flush=True)
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(a.work)],
                       capture_output=True)
    md = write_report(a.out, hashes, n_sites, cmd)
    print("\n".join(md[:11 + len(TESTS)]))


if __name__ == "__main__":
    main()
