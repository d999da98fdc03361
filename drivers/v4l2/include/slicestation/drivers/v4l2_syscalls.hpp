#pragma once
/// The system calls the V4L2 driver makes, behind an interface so tests can run the driver
/// against an emulated device (tests/hw/v4l2_emulator.hpp) instead of /dev/video*.
///
/// Contract: exactly the libc semantics. Each call returns what libc would return and sets
/// errno on failure (-1, or MAP_FAILED for mmap). `ioctl` takes the V4L2 request codes and
/// structures of <linux/videodev2.h>.
/// Threading: the driver calls these from its owning thread only.

#include <poll.h>
#include <sys/types.h>

#include <cstddef>
#include <memory>

namespace slicestation::drivers {

class V4l2Syscalls {
public:
    virtual ~V4l2Syscalls() = default;
    virtual int open(const char* path, int flags) = 0;
    virtual int close(int fd) = 0;
    virtual int ioctl(int fd, unsigned long request, void* arg) = 0;
    virtual int poll(struct pollfd* fds, nfds_t count, int timeoutMs) = 0;
    virtual void* mmap(void* addr, std::size_t length, int prot, int flags, int fd,
                       off_t offset) = 0;
    virtual int munmap(void* addr, std::size_t length) = 0;
};

/// The real calls, forwarded to libc (a stateless object).
std::shared_ptr<V4l2Syscalls> libcV4l2Syscalls();

} // namespace slicestation::drivers
