#include "slicestation/drivers/v4l2_syscalls.hpp"

#include <fcntl.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

namespace slicestation::drivers {

namespace {
class LibcSyscalls final : public V4l2Syscalls {
public:
    int open(const char* path, int flags) override { return ::open(path, flags); }
    int close(int fd) override { return ::close(fd); }
    int ioctl(int fd, unsigned long request, void* arg) override {
        return ::ioctl(fd, request, arg);
    }
    int poll(struct pollfd* fds, nfds_t count, int timeoutMs) override {
        return ::poll(fds, count, timeoutMs);
    }
    void* mmap(void* addr, std::size_t length, int prot, int flags, int fd, off_t offset) override {
        return ::mmap(addr, length, prot, flags, fd, offset);
    }
    int munmap(void* addr, std::size_t length) override { return ::munmap(addr, length); }
};
} // namespace

std::shared_ptr<V4l2Syscalls> libcV4l2Syscalls() {
    return std::make_shared<LibcSyscalls>();
}

} // namespace slicestation::drivers
