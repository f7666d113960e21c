#!/usr/bin/env bash
# System packages for the test suite on Debian 12 (bookworm):
#   user-mode-linux  /usr/bin/linux.uml, a real Linux kernel (with vcan modules) run as a
#                    process, for the vcan tests on hosts whose kernel has no SocketCAN
#                    (see tests/support/vcan_harness.py and /work/shared/VCAN.md); where it
#                    cannot boot (a CPU with AMX) .ci/install-uml.sh unpacks a newer one
#   kmod             insmod, used inside the User-Mode Linux guest
#   can-utils        candump, cansend, cangen, canplayer
#   iproute2         ip link add/set/del
#   systemd          systemd-analyze (unit file checks), systemd-networkd (vcan0 at boot)
#   gcc, libc6-dev   build the ahead-of-time estimator kernel (python -m monitor.estimation.kernels_aot,
#                    run by scripts/setup-venv.sh)
#   python3-dev      the Python headers that build needs when the venv's Python is Debian's own
#                    (a pyenv or python.org build brings its own)
#   mesa-vulkan-drivers  software Vulkan for the headless Rerun viewer (tests/sinks/test_viewer.py)
#   ShellCheck       (package shellcheck) lints the shell of the tests and scripts (scripts/test.sh runs it)
#   mmdebstrap       builds the small Debian root file system of the User-Mode Linux guest that
#                    runs the units under a real systemd (tests/systemd_guest; built once, cached
#                    in ~/.cache/motor-monitor/systemd-guest/)
# Run as root, or as a user with sudo.  Packages already installed are skipped.
set -euo pipefail

PACKAGES=(user-mode-linux kmod can-utils iproute2 systemd gcc libc6-dev python3-dev
          mesa-vulkan-drivers mmdebstrap shellcheck)

if [[ "$(id -u)" -eq 0 ]]; then
    SUDO=()
elif command -v sudo >/dev/null 2>&1; then
    SUDO=(sudo)
else
    echo "install-system.sh: must run as root (sudo is not available)" >&2
    exit 1
fi

missing=()
for pkg in "${PACKAGES[@]}"; do
    status="$(dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null || true)"
    if [[ "$status" != "installed" ]]; then
        missing+=("$pkg")
    fi
done

if [[ ${#missing[@]} -eq 0 ]]; then
    echo "install-system.sh: already installed: ${PACKAGES[*]}"
else
    echo "install-system.sh: installing: ${missing[*]}"
    "${SUDO[@]}" apt-get update -qq
    "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq -o Dpkg::Use-Pty=0 --no-install-recommends "${missing[@]}" \
        >/dev/null
fi

# Sanity checks: the UML kernel and its vcan module must be where
# tests/support/vcan_harness.py looks.
test -x /usr/bin/linux.uml || { echo "install-system.sh: /usr/bin/linux.uml missing" >&2; exit 1; }
uml_version="$(/usr/bin/linux.uml --version)"
vcan_ko="/usr/lib/uml/modules/${uml_version}/kernel/drivers/net/can/vcan.ko"
test -f "$vcan_ko" || { echo "install-system.sh: $vcan_ko missing" >&2; exit 1; }
export PATH="$PATH:/usr/sbin:/sbin"
for tool in insmod ip candump cansend systemd-analyze mmdebstrap; do
    command -v "$tool" >/dev/null \
        || { echo "install-system.sh: $tool missing" >&2; exit 1; }
done
# A UML kernel that boots here (Debian 12's cannot on a CPU with AMX): .ci/install-uml.sh
"${SUDO[@]}" bash "$(dirname "$0")/install-uml.sh"
echo "install-system.sh: ok (User-Mode Linux ${uml_version})"
