#!/usr/bin/env bash
# The Python package's tests: a virtual environment in target/pyenv with maturin, NumPy, Ray and
# pytest from PyPI, the wheel built from this checkout and installed into it (as a user would),
# then pytest on python/tests (which also drives the CLI: target/debug/ocellus, from the test
# build below, or $OCELLUS_BIN). Usage: bash python/test.sh [pytest args]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=target/pyenv
if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --disable-pip-version-check "maturin>=1.5,<2" "numpy>=1.21" "ray>=2.9" "pytest>=7"
# The CLI the tests drive: `cargo test --workspace` leaves its build in target/debug/ocellus.
# Right after that command (as in the README and CI) this is a no-op; a `cargo build --bin
# ocellus` would compile the workspace again, because the tests' dev-dependencies change the
# shared crates' features.
cargo test -q --workspace --no-run
rm -rf target/wheels
# The dev profile, which equals the test profile, and python/Cargo.toml turns on the features
# the test build has: so this reuses the compiled ocellus-engine and ocellus-nodes from the line
# above. Release wheels come from `maturin build --release`.
LOG=target/maturin-build.log
if ! "$VENV/bin/maturin" build -m python/Cargo.toml --profile dev -o target/wheels -i "$VENV/bin/python" >"$LOG" 2>&1; then
    cat "$LOG" >&2
    exit 1
fi
if grep -qE "Compiling ocellus-(engine|nodes) " "$LOG"; then
    echo "note: the wheel's build compiled ocellus-nodes again; python/Cargo.toml's extra features" \
        "no longer match those of \`cargo test --workspace\` (slower, still correct)" >&2
fi
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --force-reinstall --no-deps target/wheels/ocellus-*.whl
# Run from python/tests so `import ocellus` is the installed wheel, not the source folder.
cd python/tests
exec "../../$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
