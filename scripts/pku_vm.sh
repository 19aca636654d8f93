#!/usr/bin/env bash
# Run one command in a virtual machine whose CPU has memory protection keys,
# for hosts whose CPU has none (or hides them): QEMU's software emulation (TCG)
# implements PKU -- PKRU, RDPKRU/WRPKRU and the SEGV_PKUERR fault -- so what
# --pkeys rests on is exercised for real, only slowly (tens of times slower
# than the host). Nothing measured in it is a speed.
#
# The guest is Debian's own kernel booted over this machine's root file system
# (9p, read-write: the command sees and writes the same files), with fresh
# /tmp, /dev/shm, /proc, /sys and cgroup2 of its own and only a loopback
# network. It prints the command's output on this terminal and exits with the
# command's status.
#
#   sudo apt-get install qemu-system-x86 linux-image-amd64 busybox-static cpio
#   scripts/pku_vm.sh 'cd /work/main && .venv/bin/python -m pytest tests/test_heap_keys.py'
#
# Environment: PKU_VM_MEM (default 8G), PKU_VM_CPUS (default: this machine's),
# PKU_VM_SNAPSHOT=DIR: the guest runs on a copy of checkout DIR taken before
# it boots (all but DIR/.venv and DIR/reports, which stay this machine's, and
# the linters' and pytest's caches, which change under a running linter), so
# that a run of an hour is not changed by editing DIR meanwhile.
set -euo pipefail

[[ $# -eq 1 ]] || { echo "usage: $0 'COMMAND'" >&2; exit 2; }
command -v qemu-system-x86_64 >/dev/null || { echo "$0: needs qemu-system-x86 (apt)" >&2; exit 2; }
[[ -x /bin/busybox ]] || { echo "$0: needs busybox-static (apt)" >&2; exit 2; }
kernel=$(ls /boot/vmlinuz-* 2>/dev/null | sort -V | tail -1)
[[ -n $kernel ]] || { echo "$0: needs a Debian kernel in /boot (apt: linux-image-amd64)" >&2; exit 2; }
kver=${kernel#/boot/vmlinuz-}
mods=/lib/modules/$kver/kernel

work=$(mktemp -d /tmp/pku-vm.XXXXXX)
trap 'rm -rf "$work"' EXIT
root=$work/initramfs
mkdir -p "$root"/{bin,proc,sys,dev,mnt,modules}
cp /bin/busybox "$root/bin/busybox"
# virtio PCI and 9p over virtio, in dependency order (Debian builds them as modules).
order="drivers/virtio/virtio_ring drivers/virtio/virtio drivers/virtio/virtio_pci_legacy_dev
       drivers/virtio/virtio_pci_modern_dev drivers/virtio/virtio_pci fs/netfs/netfs
       fs/fscache/fscache net/9p/9pnet net/9p/9pnet_virtio fs/9p/9p"
for m in $order; do
    src=$mods/$m.ko
    [[ -e $src ]] || src=$src.xz
    [[ -e $src ]] || { echo "$0: $mods/$m.ko missing" >&2; exit 2; }
    case $src in *.xz) xz -dc "$src" > "$root/modules/$(basename "$m").ko" ;;
                 *) cp "$src" "$root/modules/" ;; esac
done
if [[ -n ${PKU_VM_SNAPSHOT:-} ]]; then
    # Copied here, before the guest boots: on the host it takes seconds, in
    # the guest (over 9p) minutes during which an edit could tear the copy.
    snap=$(realpath "$PKU_VM_SNAPSHOT")
    copy=$(mktemp -d /var/tmp/pku-vm-snapshot.XXXXXX)
    trap 'rm -rf "$work" "$copy"' EXIT
    tar -C "$snap" --exclude=./.venv --exclude=./reports --exclude=.mypy_cache --exclude=.ruff_cache \
        --exclude=.pytest_cache -cf - . | tar -C "$copy" -xf -
    mkdir -p "$copy/.venv" "$copy/reports"
fi
{
    if [[ -n ${PKU_VM_SNAPSHOT:-} ]]; then
        printf 'mount --bind %q %q && mount --bind %q %q || exit 1\n' \
            "$snap/.venv" "$copy/.venv" "$snap/reports" "$copy/reports"
        printf 'mount --rbind %q %q || exit 1\n' "$copy" "$snap"
    fi
    printf '%s\n' "$1"
} > "$root/command"
cat > "$root/init" <<EOF
#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
for m in $(for m in $order; do printf '%s ' "$(basename "$m")"; done); do insmod /modules/\$m.ko || exit 1; done
mount -t 9p -o trans=virtio,version=9p2000.L,msize=524288,cache=loose hostroot /mnt || exit 1
for d in proc sys dev; do mount --move /\$d /mnt/\$d; done
mount -t tmpfs tmp /mnt/tmp; mkdir -p /mnt/dev/shm /mnt/dev/pts
mount -t tmpfs shm /mnt/dev/shm; mount -t devpts pts /mnt/dev/pts
mount -t cgroup2 cgroup2 /mnt/sys/fs/cgroup 2>/dev/null
ip link set lo up; ip link set lo multicast on; ip route add 224.0.0.0/4 dev lo
hostname pku-vm
# Everything runs tens of times slower: a container may take over a minute to
# answer its first ListNodes (harness/factory.py), and a test of 60 loads
# in a row (tests/test_heap_keys.py) takes ~220 s, past pytest's 120 s.
export CLONEGUARD_READY_TIMEOUT=120
export PYTEST_ADDOPTS="-o timeout=900"
chroot /mnt /bin/bash -lc "\$(cat /command)"
echo "pku-vm: exit status \$?"
sync; poweroff -f
EOF
chmod +x "$root/init"
(cd "$root" && find . | cpio -o -H newc --quiet | gzip -1) > "$work/initramfs.gz"

# -cpu max under TCG has pku; the kernel turns on OSPKE when it sees it.
qemu-system-x86_64 -accel tcg,thread=multi -cpu max -smp "${PKU_VM_CPUS:-$(nproc)}" \
    -m "${PKU_VM_MEM:-8G}" -nographic -no-reboot -nodefaults -serial stdio \
    -kernel "$kernel" -initrd "$work/initramfs.gz" \
    -append "console=ttyS0 quiet panic=-1 rdinit=/init" \
    -virtfs local,path=/,mount_tag=hostroot,security_model=passthrough,multidevs=remap \
    | tee "$work/console" | grep -v 'pku-vm: exit status'
# Not anchored: the console's terminal escapes can precede it on its line.
status=$(sed -n 's/.*pku-vm: exit status \([0-9]*\).*/\1/p' "$work/console" | tail -1)
[[ -n $status ]] || { echo "$0: the guest did not finish (see the output above)" >&2; exit 1; }
exit "$status"
