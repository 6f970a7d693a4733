#!/bin/sh
# System libraries the tests' and benchmarks' peers need, from Debian's packages (README's test command
# and .ci/run run this first). Mitsuba 3's LLVM backend (Dr.Jit 1.5, the light-shaft speed peer) needs an
# LLVM newer than Debian 12's 14/15: on AVX-512 CPUs those abort in instruction selection (SIGABRT).
# Best effort: without root or apt-get nothing is installed, and benchmarks/_peers.py falls back to
# Mitsuba's scalar_rgb variant in a child process and says so in the benchmark's output.
for lib in /usr/lib/x86_64-linux-gnu/libLLVM-19.so /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1; do
    [ -e "$lib" ] && exit 0
done
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    if (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1; then
        exit 0
    fi
fi
echo "note: libllvm19 not installed (needs root and apt-get); Mitsuba's benchmark peer will use scalar_rgb" >&2
exit 0
