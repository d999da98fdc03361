#include "slicestation/drivers/v4l2_camera.hpp"

#include "slicestation/core/codec.hpp"
#include "slicestation/core/image_file.hpp"

#include <fcntl.h>
#include <linux/videodev2.h>
#include <sys/mman.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <optional>
#include <utility>

namespace slicestation::drivers {

using core::ErrorCode;
using core::makeError;

namespace {

/// An fd opened through the seam, closed through it once.
class SeamFd {
public:
    SeamFd() = default;
    SeamFd(V4l2Syscalls* calls, int fd) noexcept : calls_(calls), fd_(fd) {}
    SeamFd(SeamFd&& o) noexcept : calls_(o.calls_), fd_(std::exchange(o.fd_, -1)) {}
    SeamFd& operator=(SeamFd&& o) noexcept {
        if (this != &o) {
            reset();
            calls_ = o.calls_;
            fd_ = std::exchange(o.fd_, -1);
        }
        return *this;
    }
    ~SeamFd() { reset(); }
    int get() const noexcept { return fd_; }
    void reset() noexcept {
        if (fd_ >= 0)
            calls_->close(fd_);
        fd_ = -1;
    }

private:
    V4l2Syscalls* calls_ = nullptr;
    int fd_ = -1;
};

/// One mmap'ed V4L2 buffer, unmapped through the seam once.
class MappedBuffer {
public:
    MappedBuffer(V4l2Syscalls* calls, void* addr, std::size_t length) noexcept
        : calls_(calls), addr_(addr), length_(length) {}
    MappedBuffer(MappedBuffer&& o) noexcept
        : calls_(o.calls_), addr_(std::exchange(o.addr_, nullptr)), length_(o.length_) {}
    MappedBuffer& operator=(MappedBuffer&&) = delete;
    MappedBuffer(const MappedBuffer&) = delete;
    ~MappedBuffer() {
        if (addr_)
            calls_->munmap(addr_, length_);
    }
    const std::uint8_t* data() const noexcept { return static_cast<const std::uint8_t*>(addr_); }
    std::size_t length() const noexcept { return length_; }

private:
    V4l2Syscalls* calls_;
    void* addr_;
    std::size_t length_;
};

constexpr std::uint32_t kDecodable[] = {V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV,
                                        V4L2_PIX_FMT_RGB24, V4L2_PIX_FMT_MJPEG};

bool decodable(std::uint32_t fcc) {
    for (auto f : kDecodable)
        if (f == fcc)
            return true;
    return false;
}

std::string fourccName(std::uint32_t f) {
    std::string s(4, ' ');
    for (int i = 0; i < 4; ++i)
        s[static_cast<std::size_t>(i)] = static_cast<char>((f >> (8 * i)) & 0xff);
    return s;
}

/// Preference per output format: exact formats first, compressed last.
std::vector<std::uint32_t> candidates(hw::PixelFormat f) {
    switch (f) {
    case hw::PixelFormat::Mono8:
        return {V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_RGB24,
                V4L2_PIX_FMT_MJPEG};
    case hw::PixelFormat::Mono16:
        return {V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_RGB24,
                V4L2_PIX_FMT_MJPEG};
    case hw::PixelFormat::Rgb8:
        return {V4L2_PIX_FMT_RGB24, V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_GREY,
                V4L2_PIX_FMT_Y16};
    }
    return {};
}

int packedBytesPerPixel(std::uint32_t fcc) {
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
        return 0; // compressed
    }
}

} // namespace

struct V4l2Camera::Device {
    std::shared_ptr<V4l2Syscalls> calls;
    SeamFd fd; // declared before buffers: unmapped before the close
    std::vector<MappedBuffer> buffers;
    bool streaming = false;
    bool buffersRequested = false; // REQBUFS granted some: S_FMT is refused until they are freed
    std::uint32_t fourcc = 0, width = 0, height = 0, bytesPerLine = 0, sizeImage = 0;

    int xioctl(unsigned long request, void* arg) const {
        int r;
        do {
            r = calls->ioctl(fd.get(), request, arg);
        } while (r < 0 && errno == EINTR);
        return r;
    }
};

namespace {

core::Error sysError(const std::string& device, const std::string& what, int err) {
    const ErrorCode code =
        (err == ENODEV || err == ENXIO) ? ErrorCode::Disconnected : ErrorCode::IoError;
    return makeError(code, "v4l2 " + device + ": " + what + ": " + std::strerror(err), err);
}

/// Converts one buffer to the requested format. IoError when it cannot be decoded.
core::Result<hw::Frame> convert(const std::uint8_t* data, std::size_t bytesUsed, std::uint32_t fcc,
                                int w, int h, std::size_t bpl, hw::PixelFormat target) {
    try {
        cv::Mat src;
        auto* p = const_cast<std::uint8_t*>(data); // wrapped read-only
        switch (fcc) {
        case V4L2_PIX_FMT_GREY:
            src = cv::Mat(h, w, CV_8UC1, p, bpl);
            break;
        case V4L2_PIX_FMT_Y16:
            src = cv::Mat(h, w, CV_16UC1, p, bpl);
            break; // little-endian host
        case V4L2_PIX_FMT_YUYV:
            src = cv::Mat(h, w, CV_8UC2, p, bpl);
            break;
        case V4L2_PIX_FMT_RGB24:
            src = cv::Mat(h, w, CV_8UC3, p, bpl);
            break;
        case V4L2_PIX_FMT_MJPEG: {
            // The decoder allocates what the frame header claims: check it before decoding.
            const auto claimed = core::jpegFrameSize(p, bytesUsed);
            if (!claimed)
                return makeError(ErrorCode::IoError, "MJPEG frame has no JPEG frame header");
            if (claimed->width != w || claimed->height != h)
                return makeError(ErrorCode::IoError, "MJPEG frame header claims " +
                                                         std::to_string(claimed->width) + "x" +
                                                         std::to_string(claimed->height) +
                                                         ", not the negotiated size");
            auto decoded = core::decodeJpeg(
                std::span<const std::uint8_t>(p, bytesUsed),
                target == hw::PixelFormat::Rgb8 ? core::JpegPixels::Rgb : core::JpegPixels::Grey,
                "MJPEG frame");
            if (!decoded)
                return makeError(ErrorCode::IoError, decoded.error().message);
            src = std::move(*decoded);
            if (src.cols != w || src.rows != h)
                return makeError(ErrorCode::IoError, "MJPEG frame is " + std::to_string(src.cols) +
                                                         "x" + std::to_string(src.rows) +
                                                         ", not the negotiated size");
            break;
        }
        default:
            return makeError(ErrorCode::IoError, "unexpected pixel format " + fourccName(fcc));
        }
        cv::Mat out;
        const bool wantRgb = target == hw::PixelFormat::Rgb8;
        if (src.type() == CV_8UC2) {
            cv::cvtColor(src, out, wantRgb ? cv::COLOR_YUV2RGB_YUYV : cv::COLOR_YUV2GRAY_YUYV);
        } else if (src.channels() == 3) {
            if (wantRgb)
                out = src;
            else
                cv::cvtColor(src, out, cv::COLOR_RGB2GRAY);
        } else if (wantRgb) {
            cv::Mat g8 = src;
            if (src.depth() == CV_16U)
                src.convertTo(g8, CV_8U, 1.0 / 256);
            cv::cvtColor(g8, out, cv::COLOR_GRAY2RGB);
        } else {
            out = src;
        }
        if (target == hw::PixelFormat::Mono16 && out.depth() == CV_8U)
            out.convertTo(out, CV_16U, 257);
        if (target == hw::PixelFormat::Mono8 && out.depth() == CV_16U)
            out.convertTo(out, CV_8U, 1.0 / 256);
        hw::Frame f(target, w, h);
        for (int y = 0; y < h; ++y)
            std::memcpy(f.row(y), out.ptr(y), f.stride());
        return f;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::IoError, std::string("frame conversion failed: ") + e.what());
    }
}

core::Result<void> validateSettings(const hw::CameraSettings& s) {
    if (s.width < 1 || s.height < 1 || s.width > 16384 || s.height > 16384)
        return makeError(ErrorCode::InvalidArgument, "v4l2: width and height must be 1..16384 px");
    if (s.exposureUs < 1 || s.exposureUs > 10'000'000)
        return makeError(ErrorCode::InvalidArgument, "v4l2: exposure must be 1 us..10 s");
    if (!(s.analogueGain > 0 && s.analogueGain <= 1000) || !(s.redGain > 0 && s.redGain <= 100) ||
        !(s.blueGain > 0 && s.blueGain <= 100))
        return makeError(ErrorCode::InvalidArgument, "v4l2: gains must be positive and finite");
    return {};
}

} // namespace

V4l2Camera::V4l2Camera(V4l2CameraConfig config) : config_(std::move(config)) {}

V4l2Camera::~V4l2Camera() {
    stopStreaming();
}

core::Result<std::unique_ptr<V4l2Camera>> V4l2Camera::create(V4l2CameraConfig config) {
    if (config.device.empty())
        return makeError(ErrorCode::InvalidArgument, "v4l2: camera.device is empty");
    if (config.bufferCount < 1 || config.bufferCount > 32 || config.settleFrames < 0 ||
        config.staleFrames < 0 || config.maxReinitAttempts < 1 || config.pollSlice.count() < 1 ||
        !(config.gainUnitsPerX > 0) || !(config.wbUnitsPerX > 0))
        return makeError(ErrorCode::InvalidArgument,
                         "v4l2 " + config.device + ": bad driver parameters");
    if (!config.syscalls)
        config.syscalls = libcV4l2Syscalls();
    if (!config.clock)
        config.clock = std::make_shared<core::SteadyClock>();
    std::unique_ptr<V4l2Camera> cam(new V4l2Camera(std::move(config)));
    if (auto r = cam->openDevice(); !r)
        return r.error();
    return cam;
}

std::string V4l2Camera::negotiatedFourcc() const {
    return dev_ && dev_->fourcc ? fourccName(dev_->fourcc) : std::string();
}

core::Result<void> V4l2Camera::openDevice() {
    const std::string& path = config_.device;
    auto dev = std::make_unique<Device>();
    dev->calls = config_.syscalls;
    // Non-blocking: a blocking DQBUF never returns after a UVC unplug (raspberrypi/linux #1211).
    const int fd = dev->calls->open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) {
        const int err = errno;
        if (err == ENOENT || err == ENODEV || err == ENXIO)
            return makeError(ErrorCode::NotFound,
                             "v4l2: no device " + path + " (" + std::strerror(err) + ")", err);
        return sysError(path, "open", err);
    }
    dev->fd = SeamFd(dev->calls.get(), fd);
    v4l2_capability cap{};
    if (dev->xioctl(VIDIOC_QUERYCAP, &cap) < 0) {
        const int err = errno;
        if (err == ENOTTY || err == EINVAL)
            return makeError(ErrorCode::Unsupported, "v4l2: " + path + " is not a V4L2 device",
                             err);
        return sysError(path, "VIDIOC_QUERYCAP", err);
    }
    const std::uint32_t caps =
        (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (!(caps & V4L2_CAP_VIDEO_CAPTURE)) {
        if (caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE)
            return makeError(ErrorCode::Unsupported,
                             "v4l2: " + path + " is multi-planar only (not supported)");
        return makeError(ErrorCode::Unsupported,
                         "v4l2: " + path + " is not a video capture device");
    }
    if (!(caps & V4L2_CAP_STREAMING))
        return makeError(ErrorCode::Unsupported, "v4l2: " + path + " has no streaming I/O");
    dev_ = std::move(dev);
    return {};
}

void V4l2Camera::stopStreaming() noexcept {
    if (!dev_)
        return;
    if (dev_->streaming) {
        int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        dev_->xioctl(VIDIOC_STREAMOFF, &type); // best effort: the device may be gone
        dev_->streaming = false;
    }
    dev_->buffers.clear();
    if (dev_->buffersRequested) {
        dev_->buffersRequested = false;
        v4l2_requestbuffers rb{};
        rb.count = 0;
        rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        rb.memory = V4L2_MEMORY_MMAP;
        dev_->xioctl(VIDIOC_REQBUFS, &rb);
    }
}

core::Result<hw::CameraSettings> V4l2Camera::setUp(const hw::CameraSettings& wanted) {
    Device& d = *dev_;
    const std::string& path = config_.device;

    // Format: the driver may adjust anything; accept the first candidate it keeps, else the
    // first decodable format it substituted (capture-apis.md §5.2 step 3).
    std::optional<v4l2_format> chosen, substitute;
    for (std::uint32_t fcc : candidates(wanted.format)) {
        v4l2_format f{};
        f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        f.fmt.pix.width = static_cast<std::uint32_t>(wanted.width);
        f.fmt.pix.height = static_cast<std::uint32_t>(wanted.height);
        f.fmt.pix.pixelformat = fcc;
        f.fmt.pix.field = V4L2_FIELD_NONE;
        if (d.xioctl(VIDIOC_S_FMT, &f) < 0) {
            const int err = errno;
            if (err == EINVAL)
                continue; // some drivers refuse instead of adjusting
            return sysError(path, "VIDIOC_S_FMT " + fourccName(fcc), err);
        }
        if (f.fmt.pix.pixelformat == fcc) {
            chosen = f;
            break;
        }
        if (!substitute && decodable(f.fmt.pix.pixelformat))
            substitute = f;
    }
    if (!chosen && substitute) {
        v4l2_format f = *substitute;
        if (d.xioctl(VIDIOC_S_FMT, &f) < 0)
            return sysError(path, "VIDIOC_S_FMT", errno);
        if (decodable(f.fmt.pix.pixelformat))
            chosen = f;
    }
    if (!chosen)
        return makeError(ErrorCode::Unsupported,
                         "v4l2 " + path +
                             ": offers none of the formats GREY, Y16, YUYV, RGB3, MJPG");
    const v4l2_pix_format& pix = chosen->fmt.pix;
    if (pix.width < 1 || pix.height < 1)
        return makeError(ErrorCode::IoError, "v4l2 " + path + ": driver returned an empty format");
    d.fourcc = pix.pixelformat;
    d.width = pix.width;
    d.height = pix.height;
    const std::uint32_t minBpl =
        pix.width * static_cast<std::uint32_t>(packedBytesPerPixel(d.fourcc));
    d.bytesPerLine = std::max(pix.bytesperline, minBpl); // compressed formats may say 0
    d.sizeImage = pix.sizeimage;

    hw::CameraSettings used = wanted;
    used.width = static_cast<int>(d.width);
    used.height = static_cast<int>(d.height);

    // Controls: everything automatic off so tiles match (capture-apis.md §5.2 step 4).
    auto setCtrl = [&](std::uint32_t id, std::int32_t value,
                       const char* name) -> core::Result<std::optional<std::int32_t>> {
        v4l2_control c{};
        c.id = id;
        c.value = value;
        if (d.xioctl(VIDIOC_S_CTRL, &c) < 0) {
            const int err = errno;
            if (err == EINVAL)
                return std::optional<std::int32_t>(); // no such control
            if (err == ERANGE)
                return makeError(ErrorCode::InvalidArgument,
                                 "v4l2 " + path + ": " + name + " = " + std::to_string(value) +
                                     " is outside the device's range",
                                 err);
            return sysError(path, std::string("VIDIOC_S_CTRL ") + name, err);
        }
        if (d.xioctl(VIDIOC_G_CTRL, &c) < 0)
            return sysError(path, std::string("VIDIOC_G_CTRL ") + name, errno);
        return std::optional<std::int32_t>(c.value);
    };
    if (auto r = setCtrl(V4L2_CID_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL, "auto_exposure"); !r)
        return r.error();
    const auto units100 =
        static_cast<std::int32_t>(std::max<std::int64_t>(1, (wanted.exposureUs + 50) / 100));
    auto exp = setCtrl(V4L2_CID_EXPOSURE_ABSOLUTE, units100, "exposure_time_absolute");
    if (!exp)
        return exp.error();
    if (!*exp)
        return makeError(ErrorCode::Unsupported,
                         "v4l2 " + path + ": no manual exposure control (exposure_time_absolute)");
    used.exposureUs = std::int64_t{**exp} * 100;
    auto gain =
        setCtrl(V4L2_CID_GAIN,
                static_cast<std::int32_t>(std::lround(wanted.analogueGain * config_.gainUnitsPerX)),
                "gain");
    if (!gain)
        return gain.error();
    if (*gain) {
        used.analogueGain = **gain / config_.gainUnitsPerX;
    } else if (wanted.analogueGain != 1.0) {
        return makeError(ErrorCode::Unsupported,
                         "v4l2 " + path + ": no gain control, so gain must be 1");
    }
    if (auto r = setCtrl(V4L2_CID_AUTO_WHITE_BALANCE, 0, "white_balance_automatic"); !r)
        return r.error();
    used.redGain = used.blueGain = 1.0;
    if (wanted.format == hw::PixelFormat::Rgb8) {
        auto red =
            setCtrl(V4L2_CID_RED_BALANCE,
                    static_cast<std::int32_t>(std::lround(wanted.redGain * config_.wbUnitsPerX)),
                    "red_balance");
        if (!red)
            return red.error();
        auto blue =
            setCtrl(V4L2_CID_BLUE_BALANCE,
                    static_cast<std::int32_t>(std::lround(wanted.blueGain * config_.wbUnitsPerX)),
                    "blue_balance");
        if (!blue)
            return blue.error();
        if ((!*red || !*blue) && (wanted.redGain != 1.0 || wanted.blueGain != 1.0))
            return makeError(
                ErrorCode::Unsupported,
                "v4l2 " + path +
                    ": no red/blue balance controls, so white balance gains must be 1");
        if (*red)
            used.redGain = **red / config_.wbUnitsPerX;
        if (*blue)
            used.blueGain = **blue / config_.wbUnitsPerX;
    }

    // Buffers (step 5): the driver may grant fewer than asked.
    v4l2_requestbuffers rb{};
    rb.count = static_cast<std::uint32_t>(config_.bufferCount);
    rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    rb.memory = V4L2_MEMORY_MMAP;
    if (d.xioctl(VIDIOC_REQBUFS, &rb) < 0) {
        const int err = errno;
        if (err == EINVAL)
            return makeError(ErrorCode::Unsupported, "v4l2 " + path + ": no MMAP streaming", err);
        return sysError(path, "VIDIOC_REQBUFS", err);
    }
    if (rb.count < 1)
        return makeError(ErrorCode::IoError, "v4l2 " + path + ": REQBUFS granted no buffers");
    d.buffersRequested = true;
    for (std::uint32_t i = 0; i < rb.count; ++i) {
        v4l2_buffer b{};
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        b.index = i;
        if (d.xioctl(VIDIOC_QUERYBUF, &b) < 0)
            return sysError(path, "VIDIOC_QUERYBUF", errno);
        void* a = d.calls->mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, d.fd.get(),
                                b.m.offset);
        if (a == MAP_FAILED)
            return sysError(path, "mmap of buffer " + std::to_string(i), errno);
        d.buffers.emplace_back(d.calls.get(), a, b.length);
        if (d.xioctl(VIDIOC_QBUF, &b) < 0)
            return sysError(path, "VIDIOC_QBUF", errno);
    }
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (d.xioctl(VIDIOC_STREAMON, &type) < 0)
        return sysError(path, "VIDIOC_STREAMON", errno);
    d.streaming = true;
    dropRemaining_ = config_.settleFrames;
    sequenceBase_ = lastSequence_ + 1; // the driver's sequence restarts at STREAMON
    return used;
}

core::Result<hw::CameraSettings> V4l2Camera::configure(const hw::CameraSettings& settings,
                                                       std::chrono::milliseconds) {
    if (auto v = validateSettings(settings); !v)
        return v.error();
    wanted_ = settings;
    configured_ = false;
    if (!dev_) {
        if (auto r = openDevice(); !r)
            return r.error();
    }
    stopStreaming();
    auto used = setUp(settings);
    if (!used) {
        stopStreaming();
        if (used.error().code == ErrorCode::Disconnected)
            dev_.reset(); // the next capture re-opens
        return used.error();
    }
    inForce_ = *used;
    configured_ = true;
    return inForce_;
}

core::Result<void> V4l2Camera::reinitialise(core::TimePoint deadline, const std::string& why) {
    // Full teardown and re-open: re-queuing the old buffers after ENODEV fails forever
    // (ZoneMinder #3724; field-lessons.md).
    stopStreaming();
    dev_.reset();
    core::Error last = makeError(ErrorCode::Disconnected, why);
    for (int attempt = 1; attempt <= config_.maxReinitAttempts; ++attempt) {
        if (attempt > 1) {
            const auto wake = std::min(deadline, config_.clock->now() + config_.reinitDelay);
            if (!config_.clock->sleepUntil(wake, stop_))
                return makeError(ErrorCode::Cancelled, "v4l2 " + config_.device + ": stopped");
        }
        if (stop_.raised())
            return makeError(ErrorCode::Cancelled, "v4l2 " + config_.device + ": stopped");
        if (config_.clock->now() >= deadline)
            break;
        if (auto r = openDevice(); !r) {
            last = r.error();
            continue;
        }
        auto used = setUp(wanted_);
        if (!used) {
            last = used.error();
            stopStreaming();
            dev_.reset();
            if (last.code == ErrorCode::Disconnected || last.code == ErrorCode::IoError)
                continue;
            return last; // another device answered (format or controls no longer fit)
        }
        inForce_ = *used;
        ++reinitCount_;
        return {};
    }
    return makeError(ErrorCode::Disconnected,
                     "v4l2 " + config_.device + ": device lost (" + why + ") and not back after " +
                         std::to_string(config_.maxReinitAttempts) + " attempts: " + last.message,
                     last.sysErrno);
}

core::Result<hw::Frame> V4l2Camera::capture(std::chrono::milliseconds timeout) {
    stop_.clear();
    const core::TimePoint deadline = config_.clock->now() + timeout;
    if (!configured_) {
        auto r = configure(wanted_, timeout);
        if (!r && r.error().code != ErrorCode::Disconnected &&
            r.error().code != ErrorCode::NotFound)
            return r.error();
        if (!r) {
            if (auto re = reinitialise(deadline, r.error().message); !re)
                return re.error();
            configured_ = true;
        }
    } else if (!dev_) {
        if (auto r = reinitialise(deadline, "device was gone at the last capture"); !r)
            return r.error();
    }
    // Drain frames completed before this call: they may show the slide before the last move.
    Device* d = dev_.get();
    for (;;) {
        v4l2_buffer b{};
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        if (d->xioctl(VIDIOC_DQBUF, &b) < 0) {
            const int err = errno;
            if (err == EAGAIN)
                break;
            if (err == ENODEV) {
                if (auto r = reinitialise(deadline, "DQBUF: ENODEV"); !r)
                    return r.error();
                d = dev_.get();
                break;
            }
            return sysError(config_.device, "VIDIOC_DQBUF", err);
        }
        if (b.index < d->buffers.size() && d->xioctl(VIDIOC_QBUF, &b) < 0)
            return sysError(config_.device, "VIDIOC_QBUF", errno);
    }
    dropRemaining_ += config_.staleFrames;
    return waitFrame(deadline);
}

core::Result<hw::Frame> V4l2Camera::waitFrame(core::TimePoint deadline) {
    const std::string& path = config_.device;
    for (;;) {
        if (stop_.raised())
            return makeError(ErrorCode::Cancelled, "v4l2 " + path + ": stopped");
        if (!dev_) { // a requeue met ENODEV
            if (auto r = reinitialise(deadline, "QBUF: ENODEV"); !r)
                return r.error();
            continue;
        }
        const auto now = config_.clock->now();
        if (now >= deadline)
            return makeError(ErrorCode::Timeout, "v4l2 " + path + ": no frame before the deadline");
        const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - now);
        const int sliceMs =
            static_cast<int>(std::max<std::int64_t>(1, std::min(left, config_.pollSlice).count()));
        Device& d = *dev_;
        pollfd p{d.fd.get(), POLLIN, 0};
        const int n = d.calls->poll(&p, 1, sliceMs);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return sysError(path, "poll", errno);
        }
        if (n == 0)
            continue;
        if (p.revents & (POLLERR | POLLHUP | POLLNVAL)) {
            if (auto r = reinitialise(deadline, "poll: POLLERR/POLLHUP"); !r)
                return r.error();
            continue;
        }
        if (!(p.revents & POLLIN))
            continue;
        v4l2_buffer b{};
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        if (d.xioctl(VIDIOC_DQBUF, &b) < 0) {
            const int err = errno;
            if (err == EAGAIN)
                continue;
            if (err == ENODEV) {
                if (auto r = reinitialise(deadline, "DQBUF: ENODEV"); !r)
                    return r.error();
                continue;
            }
            return sysError(path, "VIDIOC_DQBUF", err);
        }
        if (b.index >= d.buffers.size())
            return makeError(ErrorCode::IoError,
                             "v4l2 " + path +
                                 ": corrupt frame: DQBUF returned unknown buffer index " +
                                 std::to_string(b.index));
        auto requeue = [&]() -> core::Result<void> {
            if (d.xioctl(VIDIOC_QBUF, &b) < 0) {
                const int err = errno;
                if (err == ENODEV) {
                    dev_.reset(); // the next capture re-opens
                    return {};
                }
                return sysError(path, "VIDIOC_QBUF", err);
            }
            return {};
        };
        const int bpp = packedBytesPerPixel(d.fourcc);
        const std::size_t needed = bpp ? std::size_t{d.bytesPerLine} * (d.height - 1) +
                                             std::size_t{d.width} * static_cast<std::size_t>(bpp)
                                       : 1;
        std::string corrupt;
        if (b.flags & V4L2_BUF_FLAG_ERROR)
            corrupt = "buffer flagged V4L2_BUF_FLAG_ERROR";
        else if (b.bytesused < needed || b.bytesused > d.buffers[b.index].length())
            corrupt = "bytesused " + std::to_string(b.bytesused) + " (expected " +
                      std::to_string(needed) + " .. " +
                      std::to_string(d.buffers[b.index].length()) + ")";
        if (!corrupt.empty()) {
            if (auto r = requeue(); !r)
                return r.error();
            return makeError(ErrorCode::IoError, "v4l2 " + path + ": corrupt frame: " + corrupt);
        }
        if (dropRemaining_ > 0) {
            --dropRemaining_;
            if (auto r = requeue(); !r)
                return r.error();
            continue;
        }
        auto frame =
            convert(d.buffers[b.index].data(), b.bytesused, d.fourcc, static_cast<int>(d.width),
                    static_cast<int>(d.height), d.bytesPerLine, wanted_.format);
        if (auto r = requeue(); !r)
            return r.error();
        if (!frame)
            return makeError(ErrorCode::IoError,
                             "v4l2 " + path + ": corrupt frame: " + frame.error().message);
        auto& m = frame->metadata;
        m.exposureUs = inForce_.exposureUs;
        m.analogueGain = inForce_.analogueGain;
        m.redGain = inForce_.redGain;
        m.blueGain = inForce_.blueGain;
        m.timestampNs = std::int64_t{b.timestamp.tv_sec} * 1'000'000'000 +
                        std::int64_t{b.timestamp.tv_usec} * 1'000;
        m.sequence = sequenceBase_ + b.sequence;
        if (m.sequence <= lastSequence_)
            m.sequence = lastSequence_ + 1;
        lastSequence_ = m.sequence;
        return frame;
    }
}

} // namespace slicestation::drivers
