#!/usr/bin/env bash
# Try the newest release of every dependency against the tests, beside the lock:
#
#   bash scripts/check_newest.sh [PYTEST ARGS]      (default: -q -m "not slow", the fast subset)
#
# In a fresh virtual environment under a temporary folder it installs torch 2.13.0 (the wheel CI
# uses), then the newest release of each package pyproject.toml names (its own caps ignored, so
# that a new major version is tried too), runs the tests and prints which versions moved and what
# failed.  It writes constraints-newest.txt: when the tests pass, moving the lock forward is
#   mv constraints-newest.txt constraints.txt
# (and, where a major version moved, raising that package's cap in pyproject.toml, which
# tests/test_packaging.py points at).
set -uo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

python3 -m venv "$work/venv"
. "$work/venv/bin/activate"
pip install --quiet torch==2.13.0 || exit 1
names=$(python3 - <<'PY'
import re, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
reqs = project["dependencies"] + [r for extra in project["optional-dependencies"].values() for r in extra]
names = {re.match(r"[A-Za-z0-9_.\-]+", r).group(0) for r in reqs}
print(" ".join(sorted(n for n in names if n not in ("mosaic-cli", "torch"))))
PY
)
pip install --quiet --upgrade $names || exit 1
pip install --quiet --no-deps -e . || exit 1
{ echo "# The versions the test suite passed with (CI's .ci/run and the README's two commands install from this file)."
  echo "# Move it forward with scripts/check_newest.sh, which installs the newest releases, runs the tests and writes the new list."
  pip freeze --exclude-editable | grep -v '^mosaic' | sed 's/^torch==\([0-9.]*\)+cpu$/torch==\1/'
} > "$root/constraints-newest.txt"

echo "versions that moved (lock -> newest):"
diff <(grep -v '^#' constraints.txt) <(grep -v '^#' constraints-newest.txt) | grep '^[<>]' || echo "  none"
status=0
if [ $# -eq 0 ]; then set -- -q -m "not slow"; fi
python -m pytest "$@" || status=$?
if [ "$status" -eq 0 ]; then
  echo "the tests pass with the newest releases: mv constraints-newest.txt constraints.txt moves the lock forward"
else
  echo "the tests above fail with the newest releases (exit $status): the lock stays; constraints-newest.txt shows what moved"
fi
exit "$status"
