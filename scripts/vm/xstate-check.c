/*
 * xstate-check: does ptrace(PTRACE_SETREGSET, NT_X86_XSTATE) take a buffer
 * shorter than this host's XSAVE area, as User-Mode Linux 6.1 passes it on
 * hosts with AMX? Sets XMM0 of a stopped child through a buffer of
 * XSTATE_CHECK_LEN bytes (default 832: legacy area, header, AVX) and reads it
 * back. Prints one line; exit 0 when the value arrived, 1 when the host
 * refused the buffer (errno), 2 on a setup failure.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/uio.h>
#include <sys/wait.h>
#include <unistd.h>

#ifndef NT_X86_XSTATE
#define NT_X86_XSTATE 0x202
#endif
#define XMM0_OFFSET 160

int main(void)
{
    static unsigned char full[1 << 16] __attribute__((aligned(64)));
    static unsigned char part[1 << 16] __attribute__((aligned(64)));
    const unsigned char pattern[16] = "online-id xstate";
    size_t len = getenv("XSTATE_CHECK_LEN") ? strtoul(getenv("XSTATE_CHECK_LEN"), 0, 10) : 832;
    struct iovec v;
    size_t host;
    int status;
    pid_t pid = fork();

    if (pid == 0) {
        ptrace(PTRACE_TRACEME, 0, 0, 0);
        raise(SIGSTOP);
        _exit(0);
    }
    if (pid < 0 || waitpid(pid, &status, 0) != pid || !WIFSTOPPED(status)) {
        printf("xstate-check: cannot trace a child\n");
        return 2;
    }
    v.iov_base = full;
    v.iov_len = sizeof full;
    if (ptrace(PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &v) != 0) {
        printf("xstate-check: PTRACE_GETREGSET: %s\n", strerror(errno));
        return 2;
    }
    host = v.iov_len;
    if (len > host)
        len = host;
    memcpy(part, full, len);
    memcpy(part + XMM0_OFFSET, pattern, sizeof pattern);
    v.iov_base = part;
    v.iov_len = len;
    if (ptrace(PTRACE_SETREGSET, pid, (void *)NT_X86_XSTATE, &v) != 0) {
        printf("xstate-check: host area %zu bytes, a %zu-byte buffer refused: errno %d (%s)\n",
               host, len, errno, strerror(errno));
        kill(pid, SIGKILL);
        return 1;
    }
    v.iov_base = full;
    v.iov_len = sizeof full;
    ptrace(PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &v);
    kill(pid, SIGKILL);
    if (memcmp(full + XMM0_OFFSET, pattern, sizeof pattern) != 0) {
        printf("xstate-check: host area %zu bytes, a %zu-byte buffer accepted but XMM0 not set\n", host, len);
        return 2;
    }
    printf("xstate-check: host area %zu bytes, a %zu-byte buffer accepted, XMM0 set\n", host, len);
    return 0;
}
