#include "slicestation/drivers/libcamera_camera.hpp"

#include "slicestation/core/codec.hpp"
#include "slicestation/core/image_file.hpp"

#include <libcamera/libcamera.h>

#include <sys/mman.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <map>
#include <mutex>

namespace slicestation::drivers {

using core::ErrorCode;
using core::makeError;
namespace lc = libcamera;

namespace {

/// libcamera aborts when a second CameraManager is created: at most one instance here.
std::atomic<bool> gManagerInUse{false};

/// One dmabuf mapping (a buffer's planes may share an fd at different offsets, not aligned:
/// map [0, end) and add the offset, as libcamera's MappedFrameBuffer does).
class DmabufMapping {
public:
    DmabufMapping(void* addr, std::size_t length) noexcept : addr_(addr), length_(length) {}
    DmabufMapping(DmabufMapping&& o) noexcept
        : addr_(std::exchange(o.addr_, nullptr)), length_(o.length_) {}
    DmabufMapping& operator=(DmabufMapping&&) = delete;
    DmabufMapping(const DmabufMapping&) = delete;
    ~DmabufMapping() {
        if (addr_)
            ::munmap(addr_, length_);
    }
    const std::uint8_t* data() const noexcept { return static_cast<const std::uint8_t*>(addr_); }

private:
    void* addr_;
    std::size_t length_;
};

bool decodable(const lc::PixelFormat& f) {
    return f == lc::formats::R8 || f == lc::formats::R10 || f == lc::formats::R12 ||
           f == lc::formats::RGB888 || f == lc::formats::BGR888 || f == lc::formats::XRGB8888 ||
           f == lc::formats::XBGR8888 || f == lc::formats::YUYV || f == lc::formats::MJPEG;
}

std::vector<lc::PixelFormat> candidates(hw::PixelFormat f) {
    switch (f) {
    case hw::PixelFormat::Mono8:
        return {lc::formats::R8, lc::formats::R12, lc::formats::R10, lc::formats::YUYV};
    case hw::PixelFormat::Mono16:
        return {lc::formats::R12, lc::formats::R10, lc::formats::R8, lc::formats::YUYV};
    case hw::PixelFormat::Rgb8:
        return {lc::formats::BGR888, lc::formats::RGB888, lc::formats::XBGR8888,
                lc::formats::XRGB8888, lc::formats::YUYV};
    }
    return {};
}

/// DRM fourcc naming is little-endian: RGB888 is B, G, R in memory; BGR888 is R, G, B.
core::Result<hw::Frame> convert(const std::uint8_t* p, std::size_t bytes,
                                const lc::PixelFormat& fmt, int w, int h, std::size_t stride,
                                hw::PixelFormat target) {
    try {
        auto* d = const_cast<std::uint8_t*>(p);
        cv::Mat rgb, grey; // one of them is filled
        if (fmt == lc::formats::R8)
            grey = cv::Mat(h, w, CV_8UC1, d, stride);
        else if (fmt == lc::formats::R10 || fmt == lc::formats::R12) {
            cv::Mat(h, w, CV_16UC1, d, stride)
                .convertTo(grey, CV_16U, fmt == lc::formats::R10 ? 64 : 16);
        } else if (fmt == lc::formats::BGR888)
            rgb = cv::Mat(h, w, CV_8UC3, d, stride);
        else if (fmt == lc::formats::RGB888)
            cv::cvtColor(cv::Mat(h, w, CV_8UC3, d, stride), rgb, cv::COLOR_BGR2RGB);
        else if (fmt == lc::formats::XBGR8888)
            cv::cvtColor(cv::Mat(h, w, CV_8UC4, d, stride), rgb, cv::COLOR_RGBA2RGB);
        else if (fmt == lc::formats::XRGB8888)
            cv::cvtColor(cv::Mat(h, w, CV_8UC4, d, stride), rgb, cv::COLOR_BGRA2RGB);
        else if (fmt == lc::formats::YUYV)
            cv::cvtColor(cv::Mat(h, w, CV_8UC2, d, stride), rgb, cv::COLOR_YUV2RGB_YUYV);
        else if (fmt == lc::formats::MJPEG) {
            // The decoder allocates what the frame header claims: check it before decoding.
            const auto claimed = core::jpegFrameSize(d, bytes);
            if (!claimed || claimed->width != w || claimed->height != h)
                return makeError(ErrorCode::IoError, "MJPEG frame cannot be decoded");
            auto decoded = core::decodeJpeg(std::span<const std::uint8_t>(d, bytes),
                                            core::JpegPixels::Rgb, "MJPEG frame");
            if (!decoded)
                return makeError(ErrorCode::IoError, decoded.error().message);
            if (decoded->cols != w || decoded->rows != h)
                return makeError(ErrorCode::IoError, "MJPEG frame cannot be decoded");
            rgb = std::move(*decoded);
        } else {
            return makeError(ErrorCode::IoError, "unexpected pixel format " + fmt.toString());
        }
        cv::Mat out;
        if (target == hw::PixelFormat::Rgb8) {
            if (rgb.empty()) {
                cv::Mat g8 = grey;
                if (grey.depth() == CV_16U)
                    grey.convertTo(g8, CV_8U, 1.0 / 256);
                cv::cvtColor(g8, rgb, cv::COLOR_GRAY2RGB);
            }
            out = rgb;
        } else {
            if (grey.empty())
                cv::cvtColor(rgb, grey, cv::COLOR_RGB2GRAY);
            if (target == hw::PixelFormat::Mono8 && grey.depth() == CV_16U)
                grey.convertTo(out, CV_8U, 1.0 / 256);
            else if (target == hw::PixelFormat::Mono16 && grey.depth() == CV_8U)
                grey.convertTo(out, CV_16U, 257);
            else
                out = grey;
        }
        hw::Frame f(target, w, h);
        for (int y = 0; y < h; ++y)
            std::memcpy(f.row(y), out.ptr(y), f.stride());
        return f;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::IoError, std::string("frame conversion failed: ") + e.what());
    }
}

} // namespace

struct LibcameraCamera::Impl {
    LibcameraCameraConfig config;
    std::unique_ptr<lc::CameraManager> manager;
    std::shared_ptr<lc::Camera> camera;
    std::string id;
    bool acquired = false;
    std::unique_ptr<lc::CameraConfiguration> cameraConfig;
    std::unique_ptr<lc::FrameBufferAllocator> allocator;
    lc::Stream* stream = nullptr;
    std::vector<std::unique_ptr<lc::Request>> requests;
    std::map<const lc::FrameBuffer*, DmabufMapping> mappings;
    std::unique_ptr<lc::ControlList> controls;
    lc::PixelFormat format;
    int width = 0, height = 0;
    std::size_t stride = 0;
    bool started = false, configured = false;
    int dropRemaining = 0;
    hw::CameraSettings wanted, inForce;

    // Shared with libcamera's thread.
    std::mutex mutex;
    std::condition_variable cv;
    std::deque<lc::Request*> completed;
    bool disconnected = false, stopRequested = false;

    ~Impl() { teardown(true); }

    // libcamera's thread: hand over, nothing else (capture-apis.md §5.1 step 6).
    void onRequestCompleted(lc::Request* r) {
        if (r->status() == lc::Request::RequestCancelled)
            return;
        {
            std::lock_guard lock(mutex);
            completed.push_back(r);
        }
        cv.notify_all();
    }
    void onDisconnected() {
        {
            std::lock_guard lock(mutex);
            disconnected = true;
        }
        cv.notify_all();
    }
    void onCameraRemoved(std::shared_ptr<lc::Camera> cam) {
        if (cam && cam->id() == id)
            onDisconnected();
    }

    void stopStream() noexcept {
        if (started && camera)
            camera->stop(); // cancels pending requests synchronously
        started = false;
        std::lock_guard lock(mutex);
        completed.clear();
    }
    void freeBuffers() noexcept {
        stopStream();
        requests.clear();
        mappings.clear();
        if (allocator && stream)
            allocator->free(stream);
        allocator.reset();
        stream = nullptr;
        configured = false;
    }
    void teardown(bool all) noexcept {
        freeBuffers();
        if (camera) {
            camera->requestCompleted.disconnect(this);
            camera->disconnected.disconnect(this);
            if (acquired)
                camera->release();
            acquired = false;
            camera.reset();
        }
        if (all && manager) {
            manager->cameraRemoved.disconnect(this);
            manager->stop();
            manager.reset();
        }
    }

    core::Result<void> acquire() {
        camera = id.empty() ? nullptr : manager->get(id);
        if (!camera) {
            return makeError(ErrorCode::NotFound, "libcamera: no camera with id \"" + id + "\"");
        }
        if (const int r = camera->acquire(); r < 0)
            return makeError(ErrorCode::IoError,
                             "libcamera " + id + ": acquire failed (in use?): " + std::strerror(-r),
                             -r);
        acquired = true;
        camera->requestCompleted.connect(this, &Impl::onRequestCompleted);
        camera->disconnected.connect(this, &Impl::onDisconnected);
        std::lock_guard lock(mutex);
        disconnected = false;
        return {};
    }

    core::Result<hw::CameraSettings> setUp(const hw::CameraSettings& s) {
        freeBuffers();
        cameraConfig = camera->generateConfiguration({lc::StreamRole::StillCapture});
        if (!cameraConfig || cameraConfig->empty())
            return makeError(ErrorCode::Unsupported,
                             "libcamera " + id + ": no still-capture configuration");
        lc::StreamConfiguration& sc = cameraConfig->at(0);
        sc.size = {static_cast<unsigned>(s.width), static_cast<unsigned>(s.height)};
        sc.bufferCount = static_cast<unsigned>(config.bufferCount);
        bool found = false;
        for (const auto& f : candidates(s.format)) {
            if (std::find(sc.formats().pixelformats().begin(), sc.formats().pixelformats().end(),
                          f) != sc.formats().pixelformats().end()) {
                sc.pixelFormat = f;
                found = true;
                break;
            }
        }
        (void)found; // otherwise keep the default and see what validate() makes of it
        if (cameraConfig->validate() == lc::CameraConfiguration::Invalid)
            return makeError(ErrorCode::Unsupported, "libcamera " + id + ": configuration invalid");
        // Adjusted is normal: re-read what libcamera settled on.
        if (!decodable(sc.pixelFormat))
            return makeError(ErrorCode::Unsupported, "libcamera " + id + ": pixel format " +
                                                         sc.pixelFormat.toString() +
                                                         " not supported");
        if (const int r = camera->configure(cameraConfig.get()); r < 0)
            return makeError(r == -ENODEV ? ErrorCode::Disconnected : ErrorCode::IoError,
                             "libcamera " + id + ": configure: " + std::strerror(-r), -r);
        format = sc.pixelFormat;
        width = static_cast<int>(sc.size.width);
        height = static_cast<int>(sc.size.height);
        stride = sc.stride;
        stream = sc.stream();
        allocator = std::make_unique<lc::FrameBufferAllocator>(camera);
        if (allocator->allocate(stream) < 0)
            return makeError(ErrorCode::IoError, "libcamera " + id + ": buffer allocation failed");
        for (const auto& fb : allocator->buffers(stream)) {
            std::size_t end = 0;
            const int fd = fb->planes()[0].fd.get();
            for (const auto& p : fb->planes())
                end = std::max<std::size_t>(end, std::size_t{p.offset} + p.length);
            void* a = ::mmap(nullptr, end, PROT_READ, MAP_SHARED, fd, 0);
            if (a == MAP_FAILED)
                return makeError(ErrorCode::IoError, "libcamera " + id + ": mmap failed", errno);
            mappings.emplace(fb.get(), DmabufMapping(a, end));
            auto req = camera->createRequest();
            if (!req || req->addBuffer(stream, fb.get()) < 0)
                return makeError(ErrorCode::IoError,
                                 "libcamera " + id + ": cannot create a request");
            requests.push_back(std::move(req));
        }
        // Manual controls so tiles match, clamped to what the camera says it takes.
        hw::CameraSettings used = s;
        used.width = width;
        used.height = height;
        const auto& info = camera->controls();
        if (auto it = info.find(&lc::controls::ExposureTime); it != info.end()) {
            used.exposureUs =
                std::clamp<std::int64_t>(s.exposureUs, it->second.min().get<std::int32_t>(),
                                         it->second.max().get<std::int32_t>());
        }
        if (auto it = info.find(&lc::controls::AnalogueGain); it != info.end()) {
            used.analogueGain = std::clamp<double>(s.analogueGain, it->second.min().get<float>(),
                                                   it->second.max().get<float>());
        }
        controls = std::make_unique<lc::ControlList>(lc::controls::controls);
        controls->set(lc::controls::AeEnable, false);
        controls->set(lc::controls::ExposureTime, static_cast<std::int32_t>(used.exposureUs));
        controls->set(lc::controls::AnalogueGain, static_cast<float>(used.analogueGain));
        controls->set(lc::controls::AwbEnable, false);
        const float gains[2] = {static_cast<float>(s.redGain), static_cast<float>(s.blueGain)};
        controls->set(lc::controls::ColourGains, lc::Span<const float, 2>(gains));
        configured = true;
        return used;
    }

    core::Result<void> startStream() {
        if (const int r = camera->start(controls.get()); r < 0)
            return makeError(r == -ENODEV ? ErrorCode::Disconnected : ErrorCode::IoError,
                             "libcamera " + id + ": start: " + std::strerror(-r), -r);
        started = true;
        for (auto& req : requests) {
            req->reuse(lc::Request::ReuseBuffers);
            req->controls().merge(*controls);
            if (const int r = camera->queueRequest(req.get()); r < 0)
                return makeError(ErrorCode::IoError,
                                 "libcamera " + id + ": queueRequest: " + std::strerror(-r), -r);
        }
        dropRemaining = config.settleFrames;
        return {};
    }

    core::Result<void> requeue(lc::Request* req) {
        req->reuse(lc::Request::ReuseBuffers);
        req->controls().merge(*controls);
        if (const int r = camera->queueRequest(req); r < 0)
            return makeError(r == -ENODEV ? ErrorCode::Disconnected : ErrorCode::IoError,
                             "libcamera " + id + ": queueRequest: " + std::strerror(-r), -r);
        return {};
    }
};

LibcameraCamera::LibcameraCamera(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

LibcameraCamera::~LibcameraCamera() {
    impl_.reset();
    gManagerInUse = false;
}

core::Result<std::vector<std::string>> LibcameraCamera::listCameras() {
    if (gManagerInUse.exchange(true))
        return makeError(ErrorCode::Unsupported,
                         "libcamera: a camera manager is already running in this process");
    std::vector<std::string> ids;
    {
        lc::CameraManager cm;
        if (const int r = cm.start(); r < 0) {
            gManagerInUse = false;
            return makeError(
                ErrorCode::IoError,
                std::string("libcamera: camera manager failed to start: ") + std::strerror(-r), -r);
        }
        for (const auto& c : cm.cameras())
            ids.push_back(c->id());
        cm.stop();
    }
    gManagerInUse = false;
    return ids;
}

core::Result<std::unique_ptr<LibcameraCamera>>
LibcameraCamera::create(LibcameraCameraConfig config) {
    if (config.bufferCount < 1 || config.settleFrames < 0 || config.maxRestarts < 0 ||
        config.frameTimeout.count() < 1)
        return makeError(ErrorCode::InvalidArgument, "libcamera: bad driver parameters");
    if (gManagerInUse.exchange(true))
        return makeError(ErrorCode::Unsupported,
                         "libcamera: only one camera per process (one CameraManager)");
    auto impl = std::make_unique<Impl>();
    impl->config = config;
    impl->manager = std::make_unique<lc::CameraManager>();
    auto fail = [&](core::Error e) -> core::Error {
        impl.reset();
        gManagerInUse = false;
        return e;
    };
    if (const int r = impl->manager->start(); r < 0)
        return fail(makeError(
            ErrorCode::IoError,
            std::string("libcamera: camera manager failed to start: ") + std::strerror(-r), -r));
    const auto cams = impl->manager->cameras();
    if (cams.empty())
        return fail(makeError(ErrorCode::NotFound,
                              "libcamera: no camera found (libcamera lists 0 cameras)"));
    impl->id = config.cameraId.empty() ? cams.front()->id() : config.cameraId;
    if (auto r = impl->acquire(); !r) {
        std::string known;
        for (const auto& c : cams)
            known += (known.empty() ? "" : ", ") + c->id();
        core::Error e = r.error();
        if (e.code == ErrorCode::NotFound)
            e.message += "; cameras: " + known;
        return fail(e);
    }
    impl->manager->cameraRemoved.connect(impl.get(), &Impl::onCameraRemoved);
    return std::unique_ptr<LibcameraCamera>(new LibcameraCamera(std::move(impl)));
}

core::Result<hw::CameraSettings> LibcameraCamera::configure(const hw::CameraSettings& s,
                                                            std::chrono::milliseconds) {
    if (s.width < 1 || s.height < 1 || s.width > 16384 || s.height > 16384)
        return makeError(ErrorCode::InvalidArgument,
                         "libcamera: width and height must be 1..16384 px");
    if (s.exposureUs < 1 || s.exposureUs > 10'000'000)
        return makeError(ErrorCode::InvalidArgument, "libcamera: exposure must be 1 us..10 s");
    if (!(s.analogueGain > 0 && s.analogueGain <= 1000) || !(s.redGain > 0 && s.redGain <= 100) ||
        !(s.blueGain > 0 && s.blueGain <= 100))
        return makeError(ErrorCode::InvalidArgument,
                         "libcamera: gains must be positive and finite");
    Impl& m = *impl_;
    m.wanted = s;
    {
        std::lock_guard lock(m.mutex);
        if (m.disconnected)
            return makeError(ErrorCode::Disconnected, "libcamera " + m.id + ": camera removed");
    }
    auto used = m.setUp(s);
    if (!used) {
        m.freeBuffers();
        return used.error();
    }
    m.inForce = *used;
    return m.inForce;
}

void LibcameraCamera::stop() noexcept {
    {
        std::lock_guard lock(impl_->mutex);
        impl_->stopRequested = true;
    }
    impl_->cv.notify_all();
}

core::Result<hw::Frame> LibcameraCamera::capture(std::chrono::milliseconds timeout) {
    Impl& m = *impl_;
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    {
        std::lock_guard lock(m.mutex);
        m.stopRequested = false;
    }
    bool gone;
    {
        std::lock_guard lock(m.mutex);
        gone = m.disconnected;
    }
    if (gone) { // removed: try once to get it back by id (USB replug re-adds it)
        m.teardown(false);
        if (auto r = m.acquire(); !r)
            return makeError(ErrorCode::Disconnected,
                             "libcamera " + m.id +
                                 ": camera removed and not back: " + r.error().message);
        auto used = m.setUp(m.wanted);
        if (!used)
            return used.error();
        m.inForce = *used;
    }
    if (!m.configured) {
        auto r = configure(m.wanted, timeout);
        if (!r)
            return r.error();
    }
    if (!m.started) {
        if (auto r = m.startStream(); !r)
            return r.error();
    }
    // Requests completed before this call may show the slide before the last move.
    std::deque<lc::Request*> stale;
    {
        std::lock_guard lock(m.mutex);
        stale.swap(m.completed);
    }
    for (auto* r : stale)
        if (auto q = m.requeue(r); !q)
            return q.error();
    m.dropRemaining += 1;
    const auto frameTimeout =
        m.config.frameTimeout + std::chrono::milliseconds(5 * m.inForce.exposureUs / 1000);
    int restarts = 0;
    for (;;) {
        lc::Request* req = nullptr;
        {
            std::unique_lock lock(m.mutex);
            const auto until = std::min(deadline, std::chrono::steady_clock::now() + frameTimeout);
            m.cv.wait_until(lock, until, [&] {
                return !m.completed.empty() || m.stopRequested || m.disconnected;
            });
            if (m.stopRequested)
                return makeError(ErrorCode::Cancelled, "libcamera " + m.id + ": stopped");
            if (m.disconnected)
                return makeError(ErrorCode::Disconnected, "libcamera " + m.id + ": camera removed");
            if (!m.completed.empty()) {
                req = m.completed.front();
                m.completed.pop_front();
            }
        }
        if (!req) {
            if (std::chrono::steady_clock::now() >= deadline)
                return makeError(ErrorCode::Timeout,
                                 "libcamera " + m.id + ": no frame before the deadline");
            // Frame timeout: stop/start (rpicam-apps PR #363), a bounded number of times.
            if (++restarts > m.config.maxRestarts)
                return makeError(ErrorCode::Timeout, "libcamera " + m.id + ": no frame after " +
                                                         std::to_string(m.config.maxRestarts) +
                                                         " restarts");
            m.stopStream();
            if (auto r = m.startStream(); !r)
                return r.error();
            continue;
        }
        lc::FrameBuffer* fb = req->buffers().begin()->second;
        const lc::FrameMetadata& md = fb->metadata();
        if (md.status != lc::FrameMetadata::FrameSuccess) {
            if (auto q = m.requeue(req); !q)
                return q.error();
            return makeError(ErrorCode::IoError, "libcamera " + m.id + ": frame " +
                                                     std::to_string(md.sequence) +
                                                     " failed (corrupt or cancelled)");
        }
        if (m.dropRemaining > 0) {
            --m.dropRemaining;
            if (auto q = m.requeue(req); !q)
                return q.error();
            continue;
        }
        const auto it = m.mappings.find(fb);
        const std::size_t bytes = md.planes().empty() ? 0 : md.planes()[0].bytesused;
        core::Result<hw::Frame> frame =
            makeError(ErrorCode::IoError, "libcamera " + m.id + ": buffer not mapped");
        if (it != m.mappings.end())
            frame = convert(it->second.data() + fb->planes()[0].offset, bytes, m.format, m.width,
                            m.height, m.stride, m.wanted.format);
        hw::FrameMetadata meta;
        meta.exposureUs = req->metadata()
                              .get(lc::controls::ExposureTime)
                              .value_or(static_cast<std::int32_t>(m.inForce.exposureUs));
        meta.analogueGain = req->metadata()
                                .get(lc::controls::AnalogueGain)
                                .value_or(static_cast<float>(m.inForce.analogueGain));
        if (auto g = req->metadata().get(lc::controls::ColourGains)) {
            meta.redGain = (*g)[0];
            meta.blueGain = (*g)[1];
        } else {
            meta.redGain = m.inForce.redGain;
            meta.blueGain = m.inForce.blueGain;
        }
        meta.timestampNs = req->metadata()
                               .get(lc::controls::SensorTimestamp)
                               .value_or(static_cast<std::int64_t>(md.timestamp));
        meta.sequence = md.sequence;
        if (auto q = m.requeue(req); !q)
            return q.error();
        if (!frame)
            return makeError(ErrorCode::IoError,
                             "libcamera " + m.id + ": corrupt frame: " + frame.error().message);
        frame->metadata = meta;
        return frame;
    }
}

} // namespace slicestation::drivers

/// The module's one entry point (openLibcameraCamera in libcamera_loader.cpp looks it up).
extern "C" const slicestation::drivers::LibcameraDriver* slst_libcamera_driver() {
    using namespace slicestation;
    static const drivers::LibcameraDriver driver{
        drivers::LibcameraDriver::kAbi,
        [](const drivers::LibcameraCameraConfig& c) -> core::Result<std::unique_ptr<hw::Camera>> {
            auto cam = drivers::LibcameraCamera::create(c);
            if (!cam)
                return cam.error();
            return std::unique_ptr<hw::Camera>(std::move(cam).value());
        },
        &drivers::LibcameraCamera::listCameras};
    return &driver;
}
