#!/bin/sh
# PID 1 of the User-Mode Linux guest that tests/linux/kernel.py boots: mounts what the bridge and
# the tests need, loads the CAN modules, then runs the agent on the console channel the host
# holds (/dev/tty1) until the host closes it, and powers off. Its variables come from the kernel
# command line (an unknown KEY=VALUE there is init's environment).
export PATH=/usr/sbin:/usr/bin:/sbin:/bin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mountpoint -q /dev || mount -t devtmpfs devtmpfs /dev
mkdir -p /dev/shm /dev/pts
mount -t tmpfs -o mode=1777 tmpfs /dev/shm
mount -t devpts devpts /dev/pts
# The host's /run is not the guest's: a tmpfs of its own, for the guest's scratch files too.
mount -t tmpfs -o mode=755 tmpfs /run
modules=/usr/lib/uml/modules/$(uname -r)/kernel
for module in net/can/can net/can/can-raw net/can/can-bcm drivers/net/can/dev/can-dev \
    net/sched/sch_netem drivers/net/can/vxcan; do
    insmod "$modules/$module.ko" || echo "uml_init: insmod $module failed"
done
insmod "$modules/drivers/net/can/vcan.ko" echo=1 || echo "uml_init: insmod vcan failed"
ip link set lo up
# Receive buffers as large as a socket asks for (candump's 8 MiB, the bridge's reader's 4 MiB):
# the guest stands still while the host runs others, and frames queue meanwhile.
echo 16777216 >/proc/sys/net/core/rmem_max
cd "$ESC_BRIDGE_ROOT/tests" || poweroff -f
"$ESC_BRIDGE_PYTHON" -m linux.agent </dev/tty1 >/dev/tty1
echo "uml_init: the agent exited with status $?"
poweroff -f
