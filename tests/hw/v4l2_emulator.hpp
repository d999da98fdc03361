#pragma once
// An emulated V4L2 capture device behind drivers::V4l2Syscalls, so V4l2Camera runs in tests
// without /dev/video*. It implements QUERYCAP, S_FMT/G_FMT (adjusting like real drivers:
// clamping, even sizes, padded lines, substituting formats), REQBUFS, QUERYBUF, QBUF, DQBUF,
// STREAMON/OFF, S_CTRL/G_CTRL, poll, mmap and munmap, on a VirtualClock (a frame takes 33 ms,
// a poll timeout advances the clock by its timeout: nothing sleeps).
// Faults: poll timeouts, unplug (POLLERR, ENODEV, then ENOENT on open until it comes back),
// corrupt buffers (short bytesused, error flag, bad index, undecodable JPEG), any ioctl failing
// with a chosen errno, open and mmap failures, fewer buffers granted.
// Single-threaded, like the driver that owns it.
#include "slicestation/core/clock.hpp"
#include "slicestation/drivers/v4l2_syscalls.hpp"

#include <linux/videodev2.h>

#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::test {

struct EmulatedV4l2Options {
    std::string path = "/dev/video-emu";
    std::uint32_t deviceCaps = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
    std::vector<std::uint32_t> formats{V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV,
                                       V4L2_PIX_FMT_RGB24, V4L2_PIX_FMT_MJPEG};
    std::uint32_t maxWidth = 1280, maxHeight = 720; ///< S_FMT clamps to these
    std::uint32_t linePaddingBytes = 0;             ///< bytesperline = width * bpp + padding
    std::uint32_t maxBuffers = 8;
    bool hasExposure = true, hasGain = true, hasWhiteBalance = true;
    bool rangeErrors = false; ///< out-of-range control values: ERANGE (true) or clamped (false)
    std::shared_ptr<core::VirtualClock> clock; ///< required
};

enum class Corruption {
    ShortBytesUsed,
    ErrorFlag,
    BadIndex,
    GarbageJpeg,
    /// MJPEG: the real frame with its SOF0 header changed to claim 30000 x 30000 px.
    JpegClaimsHugeSize
};

class EmulatedV4l2Device final : public drivers::V4l2Syscalls {
public:
    explicit EmulatedV4l2Device(EmulatedV4l2Options options);

    // Faults.
    void timeoutPolls(int count) { pollTimeouts_ = count; }
    /// The device vanishes now: the open fd gets POLLERR and ENODEV; the next `failedOpens`
    /// opens fail with ENOENT, then the device is back.
    void unplug(int failedOpens);
    /// unplug(failedOpens) instead of producing frame number `frames` from now.
    void unplugAfterFrames(int frames, int failedOpens);
    void corruptNext(Corruption kind, int count = 1);
    void failIoctl(unsigned long request, int err, int count = 1) {
        ioctlFaults_[request] = {err, count};
    }
    void failOpen(int err, int count = 1) {
        openErr_ = err;
        openFaults_ = count;
    }
    void failMmap(int count = 1) { mmapFaults_ = count; }
    void failPoll(int err) { pollErr_ = err; }
    void grantBuffers(std::uint32_t count) { grantLimit_ = count; }
    void onPoll(std::function<void()> hook) { pollHook_ = std::move(hook); }

    // Observation.
    int opens() const { return opens_; }
    int openFds() const { return static_cast<int>(fds_.size()); }
    int mappedBuffers() const;
    bool streaming() const { return streaming_; }
    std::uint64_t framesProduced() const { return produced_; }
    std::int32_t control(std::uint32_t id) const;
    const v4l2_pix_format& format() const { return fmt_; }
    /// The pixel value the emulator paints at (x, y) of frame `sequence` (8-bit grey pattern).
    static std::uint8_t pattern(std::uint32_t x, std::uint32_t y, std::uint32_t sequence);

    // V4l2Syscalls.
    int open(const char* path, int flags) override;
    int close(int fd) override;
    int ioctl(int fd, unsigned long request, void* arg) override;
    int poll(struct pollfd* fds, nfds_t count, int timeoutMs) override;
    void* mmap(void* addr, std::size_t length, int prot, int flags, int fd, off_t offset) override;
    int munmap(void* addr, std::size_t length) override;

private:
    struct Buffer {
        std::vector<std::uint8_t> memory;
        bool mapped = false, queued = false;
    };
    struct Fault {
        int err = 0;
        int count = 0;
    };
    int fail(int err) {
        errno = err;
        return -1;
    }
    bool produceFrame();
    void freeBuffers();
    int setFormat(v4l2_format& f);
    int setControl(v4l2_control& c);

    EmulatedV4l2Options o_;
    v4l2_pix_format fmt_{};
    std::map<std::uint32_t, std::int32_t> controls_;
    std::vector<std::unique_ptr<Buffer>> buffers_;
    std::vector<std::unique_ptr<Buffer>> orphans_; // freed or unplugged, still mapped by the driver
    std::deque<std::uint32_t> done_;
    std::vector<int> fds_;
    int nextFd_ = 100, liveFd_ = -1;
    bool present_ = true, streaming_ = false;
    int failedOpensLeft_ = 0, unplugInFrames_ = -1, unplugFailedOpens_ = 0;
    int pollErr_ = 0, pollTimeouts_ = 0, openFaults_ = 0, openErr_ = 0, mmapFaults_ = 0, opens_ = 0;
    std::uint32_t grantLimit_ = 1000, sequence_ = 0;
    std::uint64_t produced_ = 0;
    std::deque<Corruption> corruptions_;
    std::map<unsigned long, Fault> ioctlFaults_;
    std::function<void()> pollHook_;
};

} // namespace slicestation::test
