#!/usr/bin/env bash
# Run every hexcal test on a fresh Debian machine: install what the tests need, then
# check formatting and lints and run the whole workspace's tests.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    # Debian packages of DESIGN.md §11 used by the tests: python3 with OpenCV and YAML read
    # the calibration outputs; chromium renders the HTML report (tests/report_html.rs);
    # libaravis-dev (+ libusb-1.0-0-dev, which its .pc needs) for the `aravis` feature;
    # libclang-dev for the `v4l2` feature (bindgen generates the V4L2 bindings).
    apt_packages=(python3 python3-opencv python3-yaml chromium libaravis-dev libusb-1.0-0-dev
        libclang-dev)
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${apt_packages[@]}" >/dev/null
fi

rustup component add rustfmt clippy >/dev/null 2>&1 || true
cargo fmt --all --check
cargo clippy --workspace --all-targets -- -D warnings
cargo test --workspace
# The Aravis driver (feature `aravis`): lints, then only its loopback tests (no second
# full-workspace test run).
cargo clippy --features aravis --all-targets -- -D warnings
cargo test --features aravis --test aravis_loopback
# The V4L2 driver (feature `v4l2`): no /dev/video in CI, so lints and only its unit tests
# (a simulated node behind the driver's device trait).
cargo clippy --features v4l2 --all-targets -- -D warnings
cargo test --features v4l2 --lib rig::v4l2
# The firmware protocol must stay no_std: build it for the controller's target (RP2040).
if rustup target add thumbv6m-none-eabi >/dev/null 2>&1; then
    cargo build -p hexcal-firmware-protocol --target thumbv6m-none-eabi
else
    echo "warning: thumbv6m-none-eabi not installable here; firmware-protocol not cross-built" >&2
fi
