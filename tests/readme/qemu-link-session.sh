# Sourced from firmware/ by tests/tests/readme_commands.rs before a firmware/README.md block that
# continues the command-link session of "Driving the firmware over the command link": the QEMU
# image with its built-in stage file serving the link on 127.0.0.1:4560, host-sim built, and
# $H, $HS and $L as that section's block sets them. The test ends QEMU with the block.
cargo build --release --features qemu --bin qemu
(cd .. && cargo build --release -p host-sim)
H=${CARGO_TARGET_DIR:-../target}; HS=$H/release/host-sim
./run-qemu.sh --link 4560 "$H/thumbv7em-none-eabihf/release/qemu" &
L="$HS link --connect tcp:127.0.0.1:4560"
$L --wait 30 status > /dev/null
