#include "slicestation/sim/sim_camera.hpp"

#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstring>

namespace slicestation::sim {

using core::ErrorCode;
using core::makeError;

core::Result<cv::Mat> makeGeneratedSlide(int count, cv::Size size, std::uint64_t seed) {
    if (count < 1 || size.width < 300 || size.height < 300)
        return makeError(ErrorCode::InvalidArgument, "slide: need >= 1 section of >= 300 px");
    try {
        cv::Mat slide(size.height, size.width * count, CV_16UC1, cv::Scalar(0));
        for (int i = 0; i < count; ++i) {
            GeneratorOptions o;
            o.seed = seed + static_cast<std::uint64_t>(i);
            o.imageSize = size;
            o.landmarkCount = 0;
            auto s = generateSection(builtinAtlasPlane(0.2 + 0.6 * i / std::max(1, count - 1)), o);
            if (!s)
                return s.error();
            s->image.copyTo(slide(cv::Rect(i * size.width, 0, size.width, size.height)));
        }
        return slide;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("slide: OpenCV: ") + e.what());
    }
}

core::Result<std::unique_ptr<SimCamera>> SimCamera::create(SimCameraConfig config) {
    const int t = config.slide.type();
    if (config.slide.empty() || (t != CV_8UC1 && t != CV_16UC1 && t != CV_8UC3))
        return makeError(ErrorCode::InvalidArgument,
                         "sim camera: slide must be 8/16-bit mono or 8-bit BGR");
    if (!(config.slideUmPerPx > 0) || !(config.sensorUmPerPx > 0) ||
        config.referenceExposureUs <= 0)
        return makeError(ErrorCode::InvalidArgument,
                         "sim camera: pixel sizes and exposure must be positive");
    if (!config.stagePosition)
        return makeError(ErrorCode::InvalidArgument, "sim camera: needs the stage position source");
    return std::unique_ptr<SimCamera>(new SimCamera(std::move(config)));
}

core::Result<hw::CameraSettings> SimCamera::configure(const hw::CameraSettings& s,
                                                      std::chrono::milliseconds) {
    if (s.width < 16 || s.height < 16 || s.width > 8192 || s.height > 8192)
        return makeError(ErrorCode::InvalidArgument,
                         "sim camera: size must be 16..8192 px per side");
    if (s.exposureUs <= 0 || s.exposureUs > 10'000'000)
        return makeError(ErrorCode::InvalidArgument, "sim camera: exposure must be 1 us..10 s");
    if (!(s.analogueGain >= 1.0 && s.analogueGain <= 64.0))
        return makeError(ErrorCode::InvalidArgument, "sim camera: gain must be 1..64");
    settings_ = s;
    settings_.width &= ~1; // like many sensors: even sizes only, the caller reads back
    settings_.height &= ~1;
    return settings_;
}

core::Result<std::unique_ptr<SimCamera>> SimCamera::create(const VirtualSlide& slide,
                                                           SimCameraConfig config) {
    config.slide = slide.image;
    config.slideUmPerPx = slide.umPerPx;
    config.slideOriginXUm = slide.originXUm;
    config.slideOriginYUm = slide.originYUm;
    return create(std::move(config));
}

namespace {

/// Renders a gw x gh grid whose pixel g samples slide index a*g + b (x and y alike in a, with
/// offsets bx, by) from only the slide region it needs, as float in [0, 1].
void renderGrid(const cv::Mat& slide, double a, double bx, double by, int gw, int gh, cv::Mat& srcF,
                cv::Mat& out) {
    const double x0 = bx, x1 = a * (gw - 1) + bx, y0 = by, y1 = a * (gh - 1) + by;
    const cv::Rect all(0, 0, slide.cols, slide.rows);
    cv::Rect roi(static_cast<int>(std::floor(x0)) - 1, static_cast<int>(std::floor(y0)) - 1, 0, 0);
    roi.width = static_cast<int>(std::ceil(x1)) + 2 - roi.x;
    roi.height = static_cast<int>(std::ceil(y1)) + 2 - roi.y;
    roi &= all;
    if (roi.empty()) { // entirely off the slide: the nearest edge pixels continue
        const int cx = std::clamp(static_cast<int>(std::lround((x0 + x1) / 2)), 0, slide.cols - 2);
        const int cy = std::clamp(static_cast<int>(std::lround((y0 + y1) / 2)), 0, slide.rows - 2);
        roi = cv::Rect(std::max(0, cx), std::max(0, cy), 2, 2) & all;
    }
    cv::Mat src = slide(roi);
    double ox = roi.x, oy = roi.y, step = 1;
    // Downsampling: average whole blocks first (area), so the sensor does not alias.
    const int f = static_cast<int>(std::floor(a));
    if (f >= 2 && src.cols >= 2 * f && src.rows >= 2 * f) {
        cv::Mat small;
        cv::resize(src(cv::Rect(0, 0, src.cols / f * f, src.rows / f * f)), small,
                   cv::Size(src.cols / f, src.rows / f), 0, 0, cv::INTER_AREA);
        src = small;
        ox += (f - 1) / 2.0; // block j's centre is slide index ox + f * j + (f - 1) / 2
        oy += (f - 1) / 2.0;
        step = f;
    }
    src.convertTo(srcF, CV_32F, slide.depth() == CV_16U ? 1.0 / 65535 : 1.0 / 255);
    const cv::Mat m =
        (cv::Mat_<double>(2, 3) << a / step, 0, (bx - ox) / step, 0, a / step, (by - oy) / step);
    cv::warpAffine(srcF, out, m, cv::Size(gw, gh), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                   cv::BORDER_REPLICATE);
}

} // namespace

core::Result<hw::Frame> SimCamera::capture(std::chrono::milliseconds) {
    try {
        const hw::StagePosition pos = config_.stagePosition();
        const auto& s = settings_;
        // Slide index (pixel centres at integers) of sensor pixel u: X + k (u + 0.5 - w/2) - 0.5,
        // where X is the stage position in continuous slide pixels and k slide px per sensor px.
        const double k = config_.sensorUmPerPx / config_.slideUmPerPx;
        const double X = (pos.xUm - config_.slideOriginXUm) / config_.slideUmPerPx;
        const double Y = (pos.yUm - config_.slideOriginYUm) / config_.slideUmPerPx;
        // Defocus: distance of z from the tilted focal surface at this x, y.
        const double dz = pos.zUm - (config_.focusZUm + config_.focusTiltX * pos.xUm +
                                     config_.focusTiltY * pos.yUm);
        const double sigma = std::abs(dz) * config_.blurSigmaPxPerUm; // sensor px
        const bool blur = sigma > 0.3;
        const int margin = blur ? static_cast<int>(std::ceil(3 * sigma)) : 0;
        // Large blurs are computed on a coarser grid (sigma 4 there) and scaled back up.
        const double down = sigma > 8 ? sigma / 4 : 1.0;
        const int gw = static_cast<int>(std::ceil((s.width + 2 * margin) / down));
        const int gh = static_cast<int>(std::ceil((s.height + 2 * margin) / down));
        const double a = k * down;
        const double bx = X + k * (0.5 * down - margin - s.width / 2.0) - 0.5;
        const double by = Y + k * (0.5 * down - margin - s.height / 2.0) - 0.5;
        // Scratch images are members: re-allocating megabytes per frame costs more than the
        // arithmetic (page faults).
        auto& w = scratch_;
        renderGrid(config_.slide, a, bx, by, gw, gh, w.srcF, w.grid);
        if (blur)
            cv::GaussianBlur(w.grid, w.grid, cv::Size(), sigma / down);
        if (down == 1.0) {
            w.grid(cv::Rect(margin, margin, s.width, s.height)).copyTo(w.view);
        } else { // sensor pixel u' sits at grid coordinate (u' + 0.5 + margin) / down - 0.5
            const double off = (0.5 + margin) / down - 0.5;
            const cv::Mat m = (cv::Mat_<double>(2, 3) << 1 / down, 0, off, 0, 1 / down, off);
            cv::warpAffine(w.grid, w.view, m, cv::Size(s.width, s.height),
                           cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
        }
        cv::Mat& view = w.view;
        // Exposure and gain scale the signal; noise: shot (sqrt signal) and read, times gain.
        const double scale = double(s.exposureUs) / config_.referenceExposureUs * s.analogueGain;
        view *= scale;
        w.noise.create(view.size(), view.type());
        cv::RNG rng(0x5eed + sequence_);
        rng.fill(w.noise, cv::RNG::NORMAL, 0.0, 1.0);
        cv::max(view, 0.0, w.work);
        cv::sqrt(w.work, w.work);
        w.work.convertTo(w.work, -1, 0.01, 0.002);
        cv::multiply(w.noise, w.work, w.noise, s.analogueGain);
        view += w.noise;

        hw::Frame f(s.format, s.width, s.height);
        const int outType = s.format == hw::PixelFormat::Mono16  ? CV_16UC1
                            : s.format == hw::PixelFormat::Mono8 ? CV_8UC1
                                                                 : CV_8UC3;
        cv::Mat out(s.height, s.width, outType, f.bytes().data(),
                    f.stride()); // writes into the frame
        if (s.format == hw::PixelFormat::Mono16) {
            if (view.channels() == 3)
                cv::cvtColor(view, view, cv::COLOR_BGR2GRAY);
            view.convertTo(out, CV_16U, 65535);
        } else if (s.format == hw::PixelFormat::Mono8) {
            if (view.channels() == 3)
                cv::cvtColor(view, view, cv::COLOR_BGR2GRAY);
            view.convertTo(out, CV_8U, 255);
        } else {
            if (view.channels() == 1)
                cv::cvtColor(view, view, cv::COLOR_GRAY2RGB);
            else
                cv::cvtColor(view, view, cv::COLOR_BGR2RGB);
            cv::multiply(view, cv::Scalar(s.redGain, 1.0, s.blueGain), view);
            view.convertTo(out, CV_8UC3, 255);
        }
        assert(out.data == f.bytes().data()); // converted in place, not reallocated
        f.metadata.exposureUs = s.exposureUs;
        f.metadata.analogueGain = s.analogueGain;
        f.metadata.redGain = s.redGain;
        f.metadata.blueGain = s.blueGain;
        f.metadata.sequence = sequence_++;
        f.metadata.timestampNs = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                     std::chrono::steady_clock::now().time_since_epoch())
                                     .count();
        f.metadata.stage = pos;
        return f;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("sim camera: OpenCV: ") + e.what());
    }
}

} // namespace slicestation::sim
