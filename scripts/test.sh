#!/usr/bin/env bash
# Run every hexcal test on a fresh Debian machine: install what the tests need, then
# check formatting and lints and run the whole workspace's tests.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    # Debian packages of docs/design.md §11 used by the tests: python3 with OpenCV, YAML and
    # mrcal read the calibration outputs (tests/exports.rs), with venv and pytest for the
    # Python package's tests (crates/py); chromium renders the HTML report (tests/report_html.rs);
    # libaravis-dev (+ libusb-1.0-0-dev, which its .pc needs) for the `aravis` feature;
    # libclang-dev for the `v4l2` feature (bindgen generates the V4L2 bindings); for the
    # `window` feature the X client libraries winit and softbuffer load at run time, and
    # Xvfb, xwd (x11-apps), xwininfo (x11-utils) and xdotool for its tests.
    apt_packages=(python3 python3-venv python3-pytest python3-opencv python3-yaml python3-mrcal chromium libaravis-dev libusb-1.0-0-dev
        libclang-dev libx11-6 libx11-xcb1 libxcb1 libxcursor1 libxi6 libxkbcommon-x11-0
        xvfb x11-apps x11-utils xdotool)
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${apt_packages[@]}" >/dev/null
fi

rustup component add rustfmt clippy >/dev/null 2>&1 || true
# A fresh clone builds everything once: incremental compilation would only cost time.
export CARGO_INCREMENTAL=0
# Everything is built once, with the hardware drivers (features `aravis`, `v4l2`, `window`)
# and the benchmark harnesses (`bench`) switched on, so the driver tests run in the same
# pass as the rest: the Aravis driver through the GigE Vision loopback camera; the V4L2
# driver on a simulated node behind its device trait (no /dev/video in CI); the window
# projector, each test on its own Xvfb; and the hardware loop — loopback camera, trigger
# controller on a pty and window projector through the capture engine to decoded stacks.
features=hexcal/aravis,hexcal/loopback,hexcal/v4l2,hexcal/window,hexcal/bench
cargo fmt --all --check
cargo clippy --workspace --all-targets --features "$features" -- -D warnings
# The code a build without those features compiles instead (`cfg(not(feature = …))`).
cargo clippy -p hexcal --lib --bins -- -D warnings
cargo test --workspace --features "$features"
# The Python package (crates/py): built by maturin into a venv that sees Debian's numpy,
# OpenCV and pytest, in the same target folder and profile as the tests above (what they
# compiled with the same features is reused); then its tests.
venv="${TMPDIR:-/tmp}/hexcal-py-venv"
/usr/bin/python3 -m venv --system-site-packages "$venv"
"$venv/bin/pip" install -q "maturin>=1.5,<2"
VIRTUAL_ENV="$venv" PATH="$venv/bin:$PATH" maturin develop -q -m crates/py/Cargo.toml
"$venv/bin/python" -m pytest -q crates/py/tests
# Fuzzing regressions (docs/fuzzing.md): every corpus input once, then a seeded mutation
# run of every target, 40 s in all; a panic, a slow input or an allocation past the cap
# fails CI.
cargo run -q -p hexcal-fuzz --features "$features" -- ci --seconds 40
# Documentation: every intra-doc link resolves (drivers included).
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --features "$features"
# The firmware protocol must stay no_std: build it for the controller's target (RP2040).
if rustup target add thumbv6m-none-eabi >/dev/null 2>&1; then
    cargo build -p hexcal-firmware-protocol --target thumbv6m-none-eabi
else
    echo "warning: thumbv6m-none-eabi not installable here; firmware-protocol not cross-built" >&2
fi
