#!/bin/sh
# PID 1 of the User-Mode Linux guest that boots systemd (tests/linux/kernel.py, boot_systemd):
# makes the root an overlay (lower: the host's files through hostfs, never written; upper: the
# guest's memory), installs esc-bridge there as docs/service.md says, then becomes systemd.
#
# From the kernel command line (an unknown KEY=VALUE there is init's environment):
# ESC_BRIDGE_ROOT (the checkout, /opt/esc-bridge in the guest), ESC_BRIDGE_PYTHON (its venv's
# Python, for the tests' agent), ESC_BRIDGE_SETUP (a host directory with config.toml, the
# bridge's configuration), HOME (the host user's: the agent's dialect cache).
set -eu
export PATH=/usr/sbin:/usr/bin:/sbin:/bin
mount -t proc proc /proc
mount -t tmpfs -o mode=755 tmpfs /run
release=$(uname -r)
modules=/usr/lib/uml/modules/$release/kernel
for module in fs/overlayfs/overlay net/can/can net/can/can-raw drivers/net/can/dev/can-dev \
    net/sched/sch_netem; do
    insmod "$modules/$module.ko"
done
insmod "$modules/drivers/net/can/vcan.ko" echo=1

new=/run/overlay/root
mkdir -p /run/overlay/upper /run/overlay/work "$new"
mount -t overlay overlay -o lowerdir=/,upperdir=/run/overlay/upper,workdir=/run/overlay/work "$new"

# What the host's administrator enabled is not the vehicle's: none of it starts. tty1 is the
# tests' channel (no getty there), and the host's fstab names the host's disks.
rm -rf "$new"/etc/systemd/system/*.wants
ln -sf /dev/null "$new/etc/systemd/system/getty.target"
: >"$new/etc/fstab"
# The kernel's modules where modprobe looks for them.
mkdir -p "$new/lib/modules"
ln -sfn "/usr/lib/uml/modules/$release" "$new/lib/modules/$release"

# docs/service.md, "Install": the checkout is /opt/esc-bridge with its venv, the user, the
# configuration, the unit with the serial device deleted from its two EDIT lines (the
# autopilot is on UDP), enabled.
mkdir -p "$new/opt"
ln -sfn "$ESC_BRIDGE_ROOT" "$new/opt/esc-bridge"
useradd --root "$new" --system --shell /usr/sbin/nologin --groups dialout esc-bridge
mkdir -p "$new/etc/esc-bridge"
cp "$ESC_BRIDGE_SETUP/config.toml" "$new/etc/esc-bridge/config.toml"
cp "$new/opt/esc-bridge/config/esc-bridge.service" "$new/etc/systemd/system/"
sed -i 's/ dev-ttyAMA0\.device//' "$new/etc/systemd/system/esc-bridge.service"
# Where the unit's sandbox would hide the checkout or its venv's Python (pyenv's in /root; a
# clone in /tmp), the host's drop-in shows them again (kernel.py: _shown_again).
if [ -d "$ESC_BRIDGE_SETUP/esc-bridge.service.d" ]; then
    cp -r "$ESC_BRIDGE_SETUP/esc-bridge.service.d" "$new/etc/systemd/system/"
fi
systemctl --root="$new" enable esc-bridge.service

# can0 at boot: made by systemd-networkd from a .netdev (a vcan: no bit rate to set), brought
# up by a .network as docs/hardware.md's, without its [CAN] section.
mkdir -p "$new/etc/systemd/network"
printf '[NetDev]\nName=can0\nKind=vcan\n' >"$new/etc/systemd/network/80-can0.netdev"
printf '[Match]\nName=can0\n\n[Link]\nRequiredForOnline=no\n' \
    >"$new/etc/systemd/network/80-can.network"
systemctl --root="$new" enable systemd-networkd.service
systemctl --root="$new" disable systemd-networkd-wait-online.service

# The tests' agent on the console channel the host holds; when the host closes it, power off.
cat >"$new/etc/systemd/system/esc-bridge-test-agent.service" <<EOF
[Unit]
Description=the tests' agent on the host's channel (tests/linux/agent.py)
SuccessAction=poweroff-force
FailureAction=poweroff-force

[Service]
WorkingDirectory=$ESC_BRIDGE_ROOT/tests
Environment=ESC_BRIDGE_KERNEL=uml-systemd MAVLINK20=1 HOME=$HOME PYTHONUNBUFFERED=1
ExecStart=$ESC_BRIDGE_PYTHON -m linux.agent
StandardInput=tty-force
StandardOutput=tty
StandardError=journal+console
TTYPath=/dev/tty1
TTYReset=no
TTYVHangup=no

[Install]
WantedBy=multi-user.target
EOF
systemctl --root="$new" enable esc-bridge-test-agent.service

cd "$new"
mkdir -p .old-root
pivot_root . .old-root
mount -t proc proc /proc
umount -l /.old-root
exec /lib/systemd/systemd
