#!/usr/bin/env bash
# Dr.Jit's CPU backend needs libLLVM >= 16 (Debian's default 14/15 crash at the first render).
# Installs Debian's libllvm19 when no libLLVM >= 16 is present. drgan finds the library by itself.
set -euo pipefail
have=$(python3 - <<'PY' 2>/dev/null || true
import glob, re
found = [int(m.group(1)) for p in glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*")
         for m in [re.search(r"LLVM-?(\d+)", p)] if m]
print(max(found) if found else 0)
PY
)
if [ "${have:-0}" -ge 16 ]; then
  echo "libLLVM $have found"
  exit 0
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq libllvm19
