#!/usr/bin/env bash
# The Python package's tests, as a user gets the package: `pip install ./python` into a
# fresh virtual environment (maturin builds the extension), then pytest over
# python/tests. The tests compare with the command line, so they need the `skelid`
# binary: `cargo test` has built it (target/debug/skelid); SKELID_BIN names another.
#
# SKELID_PYTHON_PROFILE (default: dev) is the cargo profile the extension is built with:
# dev reuses what `cargo test` just compiled (a user's `pip install ./python` builds
# release). Numbers do not depend on it: the tests compare with a binary of the same
# profile, and Rust does not reorder floating-point arithmetic between profiles.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
venv=target/python-venv
rm -rf "$venv"
"$python" -m venv "$venv"
"$venv/bin/python" -m pip install -q --upgrade pip
# The build's own output goes to a log (shown if it fails), so that we can say whether
# it reused what `cargo test` compiled: it should compile only the crates the Python
# package alone uses (pyo3 and its kin, numpy, skelid-python).
log=target/python-build.log
if ! MATURIN_PEP517_ARGS="--profile ${SKELID_PYTHON_PROFILE:-dev}" \
  "$venv/bin/python" -m pip install -v "./python[test]" >"$log" 2>&1; then
  tail -n 60 "$log"
  echo "error: pip install ./python failed; its whole output is in $log" >&2
  exit 1
fi
# Crates only the Python package uses are compiled here; anything else is a crate the
# tests had compiled with other features.
again=$(grep -E '^ *Compiling ' "$log" |
  grep -cvE 'Compiling (skelid-python|pyo3[a-z-]*|numpy|target-lexicon) ' || true)
if [ "$again" -gt 0 ] && [ -x target/debug/skelid ]; then
  echo "note: the Python build compiled $again crates that cargo test had compiled" \
    "with other features ($log): see [build-dependencies] in Cargo.toml" >&2
fi
"$venv/bin/python" -c "import skelid; print('skelid', skelid.__version__, 'for Python')"
export SKELID_BIN=${SKELID_BIN:-$PWD/target/debug/skelid}
[ -x "$SKELID_BIN" ] || cargo build --bin skelid
exec "$venv/bin/python" -m pytest -q python/tests
