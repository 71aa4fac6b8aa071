/*
 * uml-xstate.so: an LD_PRELOAD shim that lets Debian bookworm's User-Mode Linux
 * (6.1) run on hosts whose XSAVE area is larger than UML's FPU buffer.
 *
 * UML keeps each guest process's FPU state in a buffer of 2696 bytes and
 * restores it with ptrace(PTRACE_SETREGSET, pid, NT_X86_XSTATE, iov). The host
 * kernel accepts that request only with the whole XSAVE area: it clamps a
 * longer buffer to its size, but a shorter one fails with EFAULT. Hosts with
 * AMX (Intel Xeon Sapphire Rapids and later: 11008 bytes) are such hosts, and
 * UML panics at boot there ("ptrace set fp regs failed, errno = 14").
 *
 * When the host refuses a short buffer, this shim reads the tracee's whole
 * area, lays the caller's buffer over its start, puts the state components
 * that lie beyond the caller's buffer (AMX tiles) into their initial state,
 * and sets the whole area. Every other call goes to glibc's ptrace unchanged.
 * UML_XSTATE_PAD=always takes that path on every call (to test it on hosts
 * that do not need it).
 */
#define _GNU_SOURCE
#include <cpuid.h>
#include <dlfcn.h>
#include <errno.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/types.h>
#include <sys/uio.h>

#ifndef NT_X86_XSTATE
#define NT_X86_XSTATE 0x202
#endif

#define XSAVE_HEADER_END 576   /* legacy area (512) + XSAVE header (64) */
#define XSTATE_BV_OFFSET 512
#define FULL_AREA_MAX (1 << 16)

typedef long (*ptrace_fn)(enum __ptrace_request, pid_t, void *, void *);

static ptrace_fn real_ptrace;
static int pad_needed;  /* the host refused a short buffer once: pad at once from then on */

static long call_real(enum __ptrace_request request, pid_t pid, void *addr, void *data)
{
    if (!real_ptrace)
        real_ptrace = (ptrace_fn)dlsym(RTLD_NEXT, "ptrace");
    return real_ptrace(request, pid, addr, data);
}

static long set_xstate_padded(pid_t pid, const struct iovec *iov)
{
    unsigned char *full;
    struct iovec whole;
    uint64_t bv;
    size_t n;
    long ret;
    int err, i;

    if (iov->iov_len < XSAVE_HEADER_END) {
        errno = EFAULT;
        return -1;
    }
    full = aligned_alloc(64, FULL_AREA_MAX);
    if (!full) {
        errno = ENOMEM;
        return -1;
    }
    whole.iov_base = full;
    whole.iov_len = FULL_AREA_MAX;
    /* The kernel shortens iov_len to the size of its XSAVE area. */
    if (call_real(PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &whole) != 0) {
        err = errno;
        free(full);
        errno = err;
        return -1;
    }
    n = iov->iov_len < whole.iov_len ? iov->iov_len : whole.iov_len;
    memcpy(full, iov->iov_base, n);
    memcpy(&bv, full + XSTATE_BV_OFFSET, sizeof bv);
    for (i = 2; i < 63; i++) {
        unsigned int size, offset, ecx, edx;
        if (!(bv & (1ULL << i)))
            continue;
        __cpuid_count(0xd, i, size, offset, ecx, edx);
        if ((size_t)offset + size > n)
            bv &= ~(1ULL << i);  /* not in the caller's buffer: initial state */
    }
    memcpy(full + XSTATE_BV_OFFSET, &bv, sizeof bv);
    ret = call_real(PTRACE_SETREGSET, pid, (void *)NT_X86_XSTATE, &whole);
    err = errno;
    free(full);
    errno = err;
    return ret;
}

long ptrace(enum __ptrace_request request, ...)
{
    va_list ap;
    pid_t pid;
    void *addr, *data;
    long ret;

    va_start(ap, request);
    pid = va_arg(ap, pid_t);
    addr = va_arg(ap, void *);
    data = va_arg(ap, void *);
    va_end(ap);

    if (request != PTRACE_SETREGSET || (uintptr_t)addr != NT_X86_XSTATE || !data)
        return call_real(request, pid, addr, data);
    if (!pad_needed && getenv("UML_XSTATE_PAD") && strcmp(getenv("UML_XSTATE_PAD"), "always") == 0)
        pad_needed = 1;
    if (pad_needed)
        return set_xstate_padded(pid, data);
    ret = call_real(request, pid, addr, data);
    if (ret != 0 && errno == EFAULT) {
        pad_needed = 1;
        return set_xstate_padded(pid, data);
    }
    return ret;
}
