#!/usr/bin/env bash
# The three regressions issue 23 names, each written into a scratch worktree of
# HEAD and run against the test file that must catch it; prints the pytest tail
# of each (every one should end in failures).  Results:
# experiments/results/mutation/PROBES.md.   Usage: bash experiments/regression_probes.sh
set -uo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
WORK="${WORK:-/tmp/jdem-probes}"
PY="${PY:-$ROOT/.venv/bin/python}"
git -C "$ROOT" worktree remove --force "$WORK" 2>/dev/null || true
git -C "$ROOT" worktree add --detach "$WORK" HEAD >/dev/null
cd "$WORK"
probe() {   # probe NAME TESTFILE FILE OLD NEW: OLD (once in FILE) becomes NEW
  echo "== $1 ($2)"
  "$PY" -c "$edit" "$3" "$4" "$5" || { echo "probe edit failed"; exit 1; }
  git diff --stat | tail -1
  PYTHONPATH="$WORK" "$PY" -m pytest -q -p no:cacheprovider -n 0 "$2" 2>&1 | tail -1
  git checkout -q .
}
edit='import sys; p, o, n = sys.argv[1:4]
s = open(p).read(); assert s.count(o) == 1, (p, o); open(p, "w").write(s.replace(o, n))'
probe "spin dropped from the contact's relative velocity" tests/test_contact_spin.py \
  jdem/contact.py 'relative_velocity(p.vel, p.angvel,' 'relative_velocity(p.vel, 0.0 * p.angvel,'
probe "contact history copied by row position" tests/test_history_reorder.py \
  jdem/neighbors.py 'contacts.shear[old_row], 0.0)' \
  'contacts.shear[jnp.minimum(jnp.arange(new_i.shape[0]), size - 1)], 0.0)'
probe "max(R1, R2) for the bond section" tests/test_bond_unequal.py \
  jdem/bond.py 'r_min = jnp.minimum(r1, r2)' 'r_min = jnp.maximum(r1, r2)'
cd "$ROOT" && git worktree remove --force "$WORK"
