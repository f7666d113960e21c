#!/usr/bin/env bash
# A User-Mode Linux kernel that boots on this host, for the vcan and systemd tests.
#
# Debian 12's user-mode-linux (6.1, and trixie's 6.12) cannot run a process on a host whose
# CPU has Intel AMX (Sapphire Rapids and later): it hands the host's ptrace an XSAVE buffer
# smaller than the host's, PTRACE_SETREGSET refuses it (EFAULT), and the guest's init dies at
# its first context switch ("userspace - ptrace set fp regs failed, errno = 14", then
# "Attempted to kill init"). Newer kernels size the buffer from the host.
#
# So: boot /usr/bin/linux.uml once with a one-line init. Where it boots, nothing more is
# done. Where it does not, Debian unstable's user-mode-linux (and the libc it needs, from
# Debian 13) are unpacked into $UML_PREFIX (default /opt/motor-monitor-uml), the kernel's
# interpreter pointed at that libc (patchelf), and that kernel booted the same way; the
# tests take it from there (tests/support/vcan_harness.py). Packages come from
# deb.debian.org through apt, with a private source list and state: the system's apt
# configuration is left as it was.
# Run as root (install-system.sh calls it).
set -euo pipefail

UML_PREFIX="${UML_PREFIX:-/opt/motor-monitor-uml}"
SYSTEM_KERNEL=/usr/bin/linux.uml

# boots KERNEL: true when its init ran (it writes a file on the host through hostfs)
boots() {
    local kernel=$1 work
    work="$(mktemp -d)"
    cat >"$work/init.sh" <<EOF
#!/bin/sh
echo booted >"$work/booted"
/sbin/halt -f
EOF
    chmod +x "$work/init.sh"
    # in a subshell: the shell's own "Aborted" line for a kernel that dies goes to the log too
    (TMPDIR="$work" timeout 120 "$kernel" mem=256M root=/dev/root rootfstype=hostfs rootflags=/ \
        rw "init=$work/init.sh" con=null con0=fd:0,fd:1 </dev/null) >"$work/kernel.log" 2>&1 || true
    local ok=1
    [[ -f "$work/booted" ]] && ok=0
    if [[ $ok -ne 0 ]]; then
        grep -a -m1 -E "ptrace set fp regs failed|Kernel panic" "$work/kernel.log" >&2 || true
    fi
    rm -rf "$work"
    return $ok
}

if [[ -x "$UML_PREFIX/usr/bin/linux.uml" ]] && boots "$UML_PREFIX/usr/bin/linux.uml"; then
    echo "install-uml.sh: using $UML_PREFIX/usr/bin/linux.uml ($("$UML_PREFIX/usr/bin/linux.uml" --version))"
    exit 0
fi
if boots "$SYSTEM_KERNEL"; then
    exit 0
fi
echo "install-uml.sh: $SYSTEM_KERNEL does not boot on this host (a CPU with AMX?);" \
    "unpacking Debian unstable's user-mode-linux into $UML_PREFIX"

apt_dir="$(mktemp -d)"
trap 'rm -rf "$apt_dir"' EXIT
mkdir -p "$apt_dir/lists/partial" "$apt_dir/cache/archives/partial" "$apt_dir/debs"
cat >"$apt_dir/sources.list" <<'EOF'
deb http://deb.debian.org/debian sid main
deb http://deb.debian.org/debian trixie main
EOF
apt_opts=(-o "Dir::Etc::sourcelist=$apt_dir/sources.list" -o "Dir::Etc::sourceparts=-"
          -o "Dir::State::lists=$apt_dir/lists" -o "Dir::Cache=$apt_dir/cache"
          -o "APT::Sandbox::User=root" -qq)
apt-get "${apt_opts[@]}" update
(cd "$apt_dir/debs" && apt-get "${apt_opts[@]}" download user-mode-linux/sid libc6/trixie)
if ! command -v patchelf >/dev/null; then
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -o Dpkg::Use-Pty=0 \
        --no-install-recommends patchelf >/dev/null
fi

rm -rf "$UML_PREFIX.new"
mkdir -p "$UML_PREFIX.new"
for deb in "$apt_dir"/debs/*.deb; do
    dpkg-deb -x "$deb" "$UML_PREFIX.new"
done
libc_dir="$UML_PREFIX/usr/lib/x86_64-linux-gnu"
patchelf --set-interpreter "$libc_dir/ld-linux-x86-64.so.2" --set-rpath "$libc_dir" \
    "$UML_PREFIX.new/usr/bin/linux.uml"
rm -rf "$UML_PREFIX"
mv "$UML_PREFIX.new" "$UML_PREFIX"

kernel="$UML_PREFIX/usr/bin/linux.uml"
version="$("$kernel" --version)"
test -f "$UML_PREFIX/usr/lib/uml/modules/$version/kernel/drivers/net/can/vcan.ko" \
    || { echo "install-uml.sh: $kernel has no vcan module" >&2; exit 1; }
boots "$kernel" || { echo "install-uml.sh: $kernel does not boot either" >&2; exit 1; }
echo "install-uml.sh: using $kernel ($version)"
