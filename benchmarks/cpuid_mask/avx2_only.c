/* A CPUID mask: the process sees an AVX2-only x86-64 CPU (x86-64-v3: AVX2 and FMA, no AVX-512, AVX-VNNI or AMX).
 *
 * Preloaded (LD_PRELOAD; benchmarks/avx2_only.sh builds and preloads it), its constructor makes the CPUID
 * instruction fault for this process (Linux arch_prctl ARCH_SET_CPUID, on CPUs whose /proc/cpuinfo lists
 * "cpuid_fault") and answers each CPUID from a SIGSEGV handler: the real answer with the bits above AVX2 cleared.
 * onnxruntime (MLAS), numpy and OpenCV choose their kernels from CPUID when they load, after this constructor, so
 * they run their AVX2 code paths on an AVX-512 machine. The silicon stays what it is (clock, caches, the width of
 * its execution units): this reproduces an AVX2-only part's instruction set, not its speed.
 *
 * What it does not cover: code that ran CPUID before the constructor (the dynamic loader and libc pick their string
 * functions first), and CPUID executed after a later SIGSEGV handler replaced this one (Python's faulthandler, as
 * pytest enables it): that CPUID then reaches the other handler. The mask names itself in the environment
 * (STREAMDET_CPUID_MASK=avx2, read by streamdet.core.cpu) so reports name the instruction set the kernels used;
 * child processes inherit LD_PRELOAD and mask themselves again (exec resets the faulting).
 */
#define _GNU_SOURCE
#include <asm/prctl.h>
#include <cpuid.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <ucontext.h>
#include <unistd.h>

#define BIT(n) (1u << (n))

/* leaf 7, subleaf 0 */
static const unsigned L7_EBX = BIT(16) | BIT(17) | BIT(21) | BIT(26) | BIT(27) | BIT(28) | BIT(30) | BIT(31);
/* AVX512 F DQ IFMA PF ER CD BW VL */
static const unsigned L7_ECX = BIT(1) | BIT(6) | BIT(11) | BIT(12) | BIT(14);
/* AVX512 VBMI VBMI2 VNNI BITALG VPOPCNTDQ */
static const unsigned L7_EDX = BIT(2) | BIT(3) | BIT(8) | BIT(22) | BIT(23) | BIT(24) | BIT(25);
/* AVX512 4VNNIW 4FMAPS VP2INTERSECT, AMX-BF16, AVX512-FP16, AMX-TILE, AMX-INT8 */
/* leaf 7, subleaf 1 */
static const unsigned L7S1_EAX = BIT(4) | BIT(5) | BIT(21) | BIT(23);
/* AVX-VNNI, AVX512-BF16, AMX-FP16, AVX-IFMA */
static const unsigned L7S1_EDX = BIT(4) | BIT(5) | BIT(10) | BIT(19);
/* AVX-VNNI-INT8, AVX-NE-CONVERT, AVX-VNNI-INT16, AVX10 */

static struct sigaction previous;

static long cpuid_enabled(int on) { return syscall(SYS_arch_prctl, ARCH_SET_CPUID, on); }

static void answer_cpuid(int sig, siginfo_t *info, void *context) {
    ucontext_t *uc = (ucontext_t *)context;
    greg_t *reg = uc->uc_mcontext.gregs;
    const unsigned char *ip = (const unsigned char *)reg[REG_RIP];
    (void)sig;
    (void)info;
    if (ip == NULL || ip[0] != 0x0f || ip[1] != 0xa2) {
        /* not a CPUID: hand the fault back to whoever handled it before (the default: a crash with its core) */
        sigaction(SIGSEGV, &previous, NULL);
        return;
    }
    unsigned leaf = (unsigned)reg[REG_RAX], subleaf = (unsigned)reg[REG_RCX];
    unsigned a, b, c, d;
    cpuid_enabled(1); /* per thread, and this thread is inside the handler: nothing else runs CPUID on it meanwhile */
    __cpuid_count(leaf, subleaf, a, b, c, d);
    cpuid_enabled(0);
    if (leaf == 7 && subleaf == 0) {
        b &= ~L7_EBX;
        c &= ~L7_ECX;
        d &= ~L7_EDX;
    } else if (leaf == 7 && subleaf == 1) {
        a &= ~L7S1_EAX;
        d &= ~L7S1_EDX;
    }
    reg[REG_RAX] = a;
    reg[REG_RBX] = b;
    reg[REG_RCX] = c;
    reg[REG_RDX] = d;
    reg[REG_RIP] += 2; /* past the two-byte CPUID */
}

__attribute__((constructor)) static void mask_cpuid(void) {
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = answer_cpuid;
    sa.sa_flags = SA_SIGINFO;
    sigemptyset(&sa.sa_mask);
    if (sigaction(SIGSEGV, &sa, &previous) != 0 || cpuid_enabled(0) != 0) {
        /* measuring with the silicon's kernels while the report says AVX2 would be worse than not running */
        fprintf(stderr, "avx2_only: this kernel or CPU cannot make CPUID fault (arch_prctl ARCH_SET_CPUID; "
                        "/proc/cpuinfo lists no cpuid_fault?): not running unmasked\n");
        _exit(125);
    }
    setenv("STREAMDET_CPUID_MASK", "avx2", 1);
}
