#!/usr/bin/env bash
# Lists the panic sites that survive optimisation in a firmware ELF (built with debug info, as the
# release profile is): every `bl` to a `core::panicking::*` function, every branch to such a `bl`,
# each mapped with addr2line to the innermost frame outside the Rust standard library.
#
# Output, one line per distinct site, sorted:   FILE:LINE<TAB>FUNCTION-IN-STD<TAB>CALLER
#   e.g. core/src/compensator.rs:266   <f32>::clamp   piezo_core::compensator::Compensator::solve
# (paths relative to the repository root; FUNCTION-IN-STD is the std function whose panic it is).
#
# usage: firmware/panic-sites.sh ELF        needs llvm-objdump (Debian package llvm) and addr2line
set -euo pipefail
elf=${1:?usage: panic-sites.sh ELF}
root=$(cd "$(dirname "$0")/.." && pwd)
objdump=$(command -v llvm-objdump || true)
[[ -n $objdump ]] || { echo "panic-sites.sh: llvm-objdump not found (apt-get install llvm)" >&2; exit 2; }
dis=$(mktemp)
trap 'rm -f "$dis"' EXIT
"$objdump" -d --demangle --no-show-raw-insn "$elf" >"$dis"

# Addresses of `bl <...panicking...>` (the panic stubs), then branches that target a stub.
sites=$(awk '
  /^ *[0-9a-f]+:/ {
    addr = $1; sub(":", "", addr)
    if ($2 ~ /^bl/ && $0 ~ /panicking/) { stub[addr] = 1; print "0x" addr }
    insn[NR] = $0
  }
  END {
    for (i in insn) {
      n = split(insn[i], f, /[ \t]+/)
      for (j = 1; j <= n; j++) if (f[j] ~ /^0x[0-9a-f]+$/) {
        t = substr(f[j], 3)
        if (t in stub) { a = f[2]; if (a == "") a = f[1]; sub(":", "", a); print "0x" a }
        break
      }
    }
  }' "$dis" | sort -u)
[[ -n $sites ]] || exit 0

for a in $sites; do
  # addr2line -i prints the inlining chain innermost first: function, file:line pairs.
  addr2line -e "$elf" -i -f -C "$a" | paste - - | awk -F'\t' -v root="$root/" '
    NR == 1 { std = $1 }
    $2 !~ /^\/rustc\// && $2 !~ /\/library\// && !done {
      loc = $2; sub(root, "", loc); sub(/ \(discriminator [0-9]+\)/, "", loc)
      caller = $1; sub(/::h[0-9a-f]{16}$/, "", caller)
      printf "%s\t%s\t%s\n", loc, std, caller; done = 1
    }'
done | sort -u
