#include "v4l2_emulator.hpp"

#include "../common/jpeg_bytes.hpp"

#include <sys/mman.h>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include <algorithm>
#include <cassert>
#include <cerrno>
#include <cstring>
#include <utility>

namespace slicestation::test {

namespace {
std::uint32_t bytesPerPixel(std::uint32_t fcc) {
    switch (fcc) {
    case V4L2_PIX_FMT_GREY:
        return 1;
    case V4L2_PIX_FMT_Y16:
        return 2;
    case V4L2_PIX_FMT_YUYV:
        return 2;
    case V4L2_PIX_FMT_RGB24:
        return 3;
    default:
        return 0;
    }
}
constexpr std::int64_t kFrameNs = 33'000'000;
constexpr off_t kOffsetStep = 1 << 20;
} // namespace

EmulatedV4l2Device::EmulatedV4l2Device(EmulatedV4l2Options options) : o_(std::move(options)) {
    assert(o_.clock);
    controls_[V4L2_CID_EXPOSURE_AUTO] = V4L2_EXPOSURE_APERTURE_PRIORITY; // like a UVC webcam
    if (o_.hasExposure)
        controls_[V4L2_CID_EXPOSURE_ABSOLUTE] = 100;
    if (o_.hasGain)
        controls_[V4L2_CID_GAIN] = 100;
    if (o_.hasWhiteBalance) {
        controls_[V4L2_CID_AUTO_WHITE_BALANCE] = 1;
        controls_[V4L2_CID_RED_BALANCE] = 1000;
        controls_[V4L2_CID_BLUE_BALANCE] = 1000;
    }
    v4l2_format f{};
    f.fmt.pix.width = 640;
    f.fmt.pix.height = 480;
    f.fmt.pix.pixelformat = o_.formats.empty() ? V4L2_PIX_FMT_GREY : o_.formats.front();
    setFormat(f);
}

std::uint8_t EmulatedV4l2Device::pattern(std::uint32_t x, std::uint32_t y, std::uint32_t sequence) {
    return static_cast<std::uint8_t>((x / 4 + y / 4 + sequence * 7) & 0xff);
}

void EmulatedV4l2Device::unplug(int failedOpens) {
    present_ = false;
    failedOpensLeft_ = failedOpens;
    streaming_ = false;
    done_.clear();
    for (auto& b : buffers_)
        orphans_.push_back(std::move(b));
    buffers_.clear();
    liveFd_ = -1; // every fd open now is stale
}

void EmulatedV4l2Device::unplugAfterFrames(int frames, int failedOpens) {
    unplugInFrames_ = frames;
    unplugFailedOpens_ = failedOpens;
}

void EmulatedV4l2Device::corruptNext(Corruption kind, int count) {
    for (int i = 0; i < count; ++i)
        corruptions_.push_back(kind);
}

int EmulatedV4l2Device::mappedBuffers() const {
    int n = 0;
    for (const auto& b : buffers_)
        n += b->mapped;
    for (const auto& b : orphans_)
        n += b->mapped;
    return n;
}

std::int32_t EmulatedV4l2Device::control(std::uint32_t id) const {
    auto it = controls_.find(id);
    return it == controls_.end() ? -1 : it->second;
}

int EmulatedV4l2Device::open(const char* path, int) {
    ++opens_;
    if (openFaults_ > 0) {
        --openFaults_;
        return fail(openErr_);
    }
    if (o_.path != path)
        return fail(ENOENT);
    if (!present_) {
        if (failedOpensLeft_ > 0) {
            --failedOpensLeft_;
            return fail(ENOENT);
        }
        present_ = true; // plugged back in
    }
    const int fd = nextFd_++;
    fds_.push_back(fd);
    liveFd_ = fd;
    return fd;
}

int EmulatedV4l2Device::close(int fd) {
    auto it = std::find(fds_.begin(), fds_.end(), fd);
    if (it == fds_.end())
        return fail(EBADF);
    fds_.erase(it);
    if (fd == liveFd_) { // closing frees the queue, as in the kernel
        streaming_ = false;
        freeBuffers();
        liveFd_ = -1;
    }
    return 0;
}

void EmulatedV4l2Device::freeBuffers() {
    done_.clear();
    for (auto& b : buffers_)
        if (b->mapped)
            orphans_.push_back(std::move(b));
    buffers_.clear();
}

int EmulatedV4l2Device::setFormat(v4l2_format& f) {
    auto& p = f.fmt.pix;
    if (std::find(o_.formats.begin(), o_.formats.end(), p.pixelformat) == o_.formats.end())
        p.pixelformat = o_.formats.front(); // substitute, as drivers do
    p.width = std::clamp<std::uint32_t>(p.width, 16, o_.maxWidth) & ~1U;
    p.height = std::clamp<std::uint32_t>(p.height, 16, o_.maxHeight) & ~1U;
    p.field = V4L2_FIELD_NONE;
    const std::uint32_t bpp = bytesPerPixel(p.pixelformat);
    p.bytesperline = bpp ? p.width * bpp + o_.linePaddingBytes : 0;
    p.sizeimage = bpp ? p.bytesperline * p.height : p.width * p.height * 2;
    fmt_ = p;
    return 0;
}

int EmulatedV4l2Device::setControl(v4l2_control& c) {
    auto it = controls_.find(c.id);
    if (it == controls_.end())
        return fail(EINVAL);
    std::int32_t lo = 0, hi = 10'000;
    if (c.id == V4L2_CID_EXPOSURE_AUTO)
        hi = 3;
    if (c.id == V4L2_CID_EXPOSURE_ABSOLUTE)
        lo = 1;
    if (c.id == V4L2_CID_GAIN)
        hi = 1'000;
    if (c.id == V4L2_CID_AUTO_WHITE_BALANCE)
        hi = 1;
    if (c.value < lo || c.value > hi) {
        if (o_.rangeErrors)
            return fail(ERANGE);
        c.value = std::clamp(c.value, lo, hi);
    }
    it->second = c.value;
    return 0;
}

bool EmulatedV4l2Device::produceFrame() {
    if (unplugInFrames_ == 0) {
        unplugInFrames_ = -1;
        unplug(unplugFailedOpens_);
        return false;
    }
    auto it =
        std::find_if(buffers_.begin(), buffers_.end(), [](const auto& b) { return b->queued; });
    if (it == buffers_.end())
        return false;
    if (unplugInFrames_ > 0)
        --unplugInFrames_;
    o_.clock->advance(std::chrono::nanoseconds(kFrameNs));
    Buffer& b = **it;
    b.queued = false;
    const std::uint32_t seq = sequence_;
    const std::uint32_t w = fmt_.width, h = fmt_.height, bpl = fmt_.bytesperline;
    std::uint8_t* m = b.memory.data();
    switch (fmt_.pixelformat) {
    case V4L2_PIX_FMT_GREY:
        for (std::uint32_t y = 0; y < h; ++y)
            for (std::uint32_t x = 0; x < w; ++x)
                m[y * bpl + x] = pattern(x, y, seq);
        break;
    case V4L2_PIX_FMT_Y16:
        for (std::uint32_t y = 0; y < h; ++y)
            for (std::uint32_t x = 0; x < w; ++x) {
                const std::uint16_t v = static_cast<std::uint16_t>(pattern(x, y, seq) << 8);
                std::memcpy(m + y * bpl + 2 * x, &v, 2); // little-endian, as V4L2 Y16
            }
        break;
    case V4L2_PIX_FMT_YUYV:
        for (std::uint32_t y = 0; y < h; ++y)
            for (std::uint32_t x = 0; x < w; ++x) {
                m[y * bpl + 2 * x] = pattern(x, y, seq);
                m[y * bpl + 2 * x + 1] = 128; // U, V neutral: grey
            }
        break;
    case V4L2_PIX_FMT_RGB24:
        for (std::uint32_t y = 0; y < h; ++y)
            for (std::uint32_t x = 0; x < w; ++x)
                for (int c = 0; c < 3; ++c)
                    m[y * bpl + 3 * x + static_cast<std::uint32_t>(c)] = pattern(x, y, seq);
        break;
    default:
        break; // MJPEG: encoded at DQBUF
    }
    done_.push_back(static_cast<std::uint32_t>(it - buffers_.begin()));
    ++sequence_;
    ++produced_;
    return true;
}

int EmulatedV4l2Device::ioctl(int fd, unsigned long request, void* arg) {
    if (std::find(fds_.begin(), fds_.end(), fd) == fds_.end())
        return fail(EBADF);
    if (fd != liveFd_)
        return fail(ENODEV); // opened before an unplug
    if (auto it = ioctlFaults_.find(request); it != ioctlFaults_.end() && it->second.count > 0) {
        --it->second.count;
        return fail(it->second.err);
    }
    switch (request) {
    case VIDIOC_QUERYCAP: {
        auto* c = static_cast<v4l2_capability*>(arg);
        *c = {};
        std::strncpy(reinterpret_cast<char*>(c->driver), "emulated", sizeof c->driver - 1);
        c->device_caps = o_.deviceCaps;
        c->capabilities = o_.deviceCaps | V4L2_CAP_DEVICE_CAPS;
        return 0;
    }
    case VIDIOC_S_FMT: {
        auto* f = static_cast<v4l2_format*>(arg);
        if (f->type != V4L2_BUF_TYPE_VIDEO_CAPTURE)
            return fail(EINVAL);
        if (streaming_ || !buffers_.empty())
            return fail(EBUSY);
        return setFormat(*f);
    }
    case VIDIOC_G_FMT: {
        auto* f = static_cast<v4l2_format*>(arg);
        f->fmt.pix = fmt_;
        return 0;
    }
    case VIDIOC_REQBUFS: {
        auto* r = static_cast<v4l2_requestbuffers*>(arg);
        if (r->memory != V4L2_MEMORY_MMAP)
            return fail(EINVAL);
        if (streaming_)
            return fail(EBUSY);
        freeBuffers();
        r->count = std::min({r->count, o_.maxBuffers, grantLimit_});
        for (std::uint32_t i = 0; i < r->count; ++i) {
            buffers_.push_back(std::make_unique<Buffer>());
            buffers_.back()->memory.assign(fmt_.sizeimage, 0);
        }
        return 0;
    }
    case VIDIOC_QUERYBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (b->index >= buffers_.size())
            return fail(EINVAL);
        b->length = static_cast<std::uint32_t>(buffers_[b->index]->memory.size());
        b->m.offset = static_cast<std::uint32_t>(b->index * kOffsetStep);
        return 0;
    }
    case VIDIOC_QBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (b->index >= buffers_.size() || buffers_[b->index]->queued)
            return fail(EINVAL);
        if (std::find(done_.begin(), done_.end(), b->index) != done_.end())
            return fail(EINVAL);
        buffers_[b->index]->queued = true;
        return 0;
    }
    case VIDIOC_DQBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (!streaming_)
            return fail(EINVAL);
        if (done_.empty())
            return fail(EAGAIN);
        const std::uint32_t index = done_.front();
        done_.pop_front();
        Buffer& buf = *buffers_[index];
        b->index = index;
        b->flags = V4L2_BUF_FLAG_DONE | V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;
        b->bytesused = fmt_.sizeimage;
        b->sequence = sequence_ - 1 - static_cast<std::uint32_t>(done_.size());
        const auto ns = o_.clock->now().time_since_epoch().count();
        b->timestamp.tv_sec = ns / 1'000'000'000;
        b->timestamp.tv_usec = (ns % 1'000'000'000) / 1000;
        if (fmt_.pixelformat == V4L2_PIX_FMT_MJPEG) {
            cv::Mat img(static_cast<int>(fmt_.height), static_cast<int>(fmt_.width), CV_8UC1);
            for (int y = 0; y < img.rows; ++y)
                for (int x = 0; x < img.cols; ++x)
                    img.at<std::uint8_t>(y, x) = pattern(
                        static_cast<std::uint32_t>(x), static_cast<std::uint32_t>(y), b->sequence);
            std::vector<std::uint8_t> jpeg;
            cv::imencode(".jpg", img, jpeg, {cv::IMWRITE_JPEG_QUALITY, 98});
            assert(jpeg.size() <= buf.memory.size());
            std::memcpy(buf.memory.data(), jpeg.data(), jpeg.size());
            b->bytesused = static_cast<std::uint32_t>(jpeg.size());
        }
        if (!corruptions_.empty()) {
            const Corruption c = corruptions_.front();
            corruptions_.pop_front();
            switch (c) {
            case Corruption::ShortBytesUsed:
                b->bytesused = fmt_.pixelformat == V4L2_PIX_FMT_MJPEG ? 0 : 10;
                break;
            case Corruption::ErrorFlag:
                b->flags |= V4L2_BUF_FLAG_ERROR;
                break;
            case Corruption::BadIndex:
                b->index = 99;
                break;
            case Corruption::GarbageJpeg:
                std::memset(buf.memory.data(), 0x5a, 200);
                b->bytesused = 200;
                break;
            case Corruption::JpegClaimsHugeSize:
                if (std::uint8_t* sof = testing_jpeg::findSof0(buf.memory.data(), b->bytesused))
                    testing_jpeg::claimSize(sof, 30000, 30000);
                break;
            }
        }
        return 0;
    }
    case VIDIOC_STREAMON:
        if (buffers_.empty())
            return fail(EINVAL);
        streaming_ = true;
        sequence_ = 0;
        return 0;
    case VIDIOC_STREAMOFF:
        streaming_ = false;
        done_.clear();
        for (auto& b : buffers_)
            b->queued = false;
        return 0;
    case VIDIOC_S_CTRL:
        return setControl(*static_cast<v4l2_control*>(arg));
    case VIDIOC_G_CTRL: {
        auto* c = static_cast<v4l2_control*>(arg);
        auto it = controls_.find(c->id);
        if (it == controls_.end())
            return fail(EINVAL);
        c->value = it->second;
        return 0;
    }
    default:
        return fail(ENOTTY);
    }
}

int EmulatedV4l2Device::poll(struct pollfd* fds, nfds_t count, int timeoutMs) {
    assert(count == 1);
    (void)count;
    if (pollHook_)
        pollHook_();
    if (pollErr_)
        return fail(std::exchange(pollErr_, 0));
    pollfd& p = fds[0];
    p.revents = 0;
    if (std::find(fds_.begin(), fds_.end(), p.fd) == fds_.end()) {
        p.revents = POLLNVAL;
        return 1;
    }
    if (p.fd != liveFd_ || !streaming_) { // unplugged, or not streaming: POLLERR as the kernel says
        p.revents = POLLERR;
        return 1;
    }
    if (pollTimeouts_ > 0) {
        --pollTimeouts_;
        o_.clock->advance(std::chrono::milliseconds(timeoutMs));
        return 0;
    }
    if (done_.empty() && !produceFrame()) {
        if (p.fd != liveFd_) { // unplugged while producing
            p.revents = POLLERR;
            return 1;
        }
        o_.clock->advance(std::chrono::milliseconds(timeoutMs)); // nothing queued: no frame comes
        return 0;
    }
    p.revents = POLLIN;
    return 1;
}

void* EmulatedV4l2Device::mmap(void*, std::size_t length, int, int, int fd, off_t offset) {
    if (fd != liveFd_) {
        errno = ENODEV;
        return MAP_FAILED;
    }
    if (mmapFaults_ > 0) {
        --mmapFaults_;
        errno = ENOMEM;
        return MAP_FAILED;
    }
    const auto index = static_cast<std::size_t>(offset / kOffsetStep);
    if (offset % kOffsetStep || index >= buffers_.size() ||
        length > buffers_[index]->memory.size()) {
        errno = EINVAL;
        return MAP_FAILED;
    }
    buffers_[index]->mapped = true;
    return buffers_[index]->memory.data();
}

int EmulatedV4l2Device::munmap(void* addr, std::size_t) {
    for (auto* list : {&buffers_, &orphans_})
        for (auto& b : *list)
            if (b && b->mapped && b->memory.data() == addr) {
                b->mapped = false;
                return 0;
            }
    return fail(EINVAL);
}

} // namespace slicestation::test
