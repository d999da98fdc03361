#include "slicestation/sim/sim_camera.hpp"

#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <cmath>

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
            if (!s) return s.error();
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
        return makeError(ErrorCode::InvalidArgument, "sim camera: slide must be 8/16-bit mono or 8-bit BGR");
    if (!(config.slideUmPerPx > 0) || !(config.sensorUmPerPx > 0) || config.referenceExposureUs <= 0)
        return makeError(ErrorCode::InvalidArgument, "sim camera: pixel sizes and exposure must be positive");
    if (!config.stagePosition)
        return makeError(ErrorCode::InvalidArgument, "sim camera: needs the stage position source");
    return std::unique_ptr<SimCamera>(new SimCamera(std::move(config)));
}

core::Result<hw::CameraSettings> SimCamera::configure(const hw::CameraSettings& s, std::chrono::milliseconds) {
    if (s.width < 16 || s.height < 16 || s.width > 8192 || s.height > 8192)
        return makeError(ErrorCode::InvalidArgument, "sim camera: size must be 16..8192 px per side");
    if (s.exposureUs <= 0 || s.exposureUs > 10'000'000)
        return makeError(ErrorCode::InvalidArgument, "sim camera: exposure must be 1 us..10 s");
    if (!(s.analogueGain >= 1.0 && s.analogueGain <= 64.0))
        return makeError(ErrorCode::InvalidArgument, "sim camera: gain must be 1..64");
    settings_ = s;
    settings_.width &= ~1; // like many sensors: even sizes only, the caller reads back
    settings_.height &= ~1;
    return settings_;
}

core::Result<hw::Frame> SimCamera::capture(std::chrono::milliseconds) {
    try {
        const hw::StagePosition pos = config_.stagePosition();
        const auto& s = settings_;
        // Field of view centred on the stage position, slide px -> sensor px.
        const double k = config_.sensorUmPerPx / config_.slideUmPerPx;
        const double cx = pos.xUm / config_.slideUmPerPx, cy = pos.yUm / config_.slideUmPerPx;
        cv::Mat m = (cv::Mat_<double>(2, 3) << k, 0, cx - k * s.width / 2.0, 0, k, cy - k * s.height / 2.0);
        cv::Mat slideF;
        config_.slide.convertTo(slideF, CV_32F, config_.slide.depth() == CV_16U ? 1.0 / 65535 : 1.0 / 255);
        cv::Mat view;
        cv::warpAffine(slideF, view, m, cv::Size(s.width, s.height), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                       cv::BORDER_CONSTANT, cv::Scalar::all(0));
        // Defocus: distance of z from the tilted focal surface at this x, y.
        const double dz = pos.zUm - (config_.focusZUm + config_.focusTiltX * pos.xUm + config_.focusTiltY * pos.yUm);
        const double sigma = std::abs(dz) * config_.blurSigmaPxPerUm;
        if (sigma > 0.3) cv::GaussianBlur(view, view, cv::Size(), sigma);
        // Exposure and gain scale the signal; noise: shot (sqrt signal) and read, times gain.
        const double scale = double(s.exposureUs) / config_.referenceExposureUs * s.analogueGain;
        view *= scale;
        cv::Mat noise(view.size(), view.type());
        cv::RNG rng(0x5eed + sequence_);
        rng.fill(noise, cv::RNG::NORMAL, 0.0, 1.0);
        cv::Mat sq;
        cv::sqrt(cv::max(view, 0.0), sq);
        view += noise.mul(sq * 0.01 + 0.002) * s.analogueGain;

        hw::Frame f(s.format, s.width, s.height);
        cv::Mat out;
        if (s.format == hw::PixelFormat::Mono16) {
            if (view.channels() == 3) cv::cvtColor(view, view, cv::COLOR_BGR2GRAY);
            view.convertTo(out, CV_16U, 65535);
        } else if (s.format == hw::PixelFormat::Mono8) {
            if (view.channels() == 3) cv::cvtColor(view, view, cv::COLOR_BGR2GRAY);
            view.convertTo(out, CV_8U, 255);
        } else {
            if (view.channels() == 1) cv::cvtColor(view, view, cv::COLOR_GRAY2RGB);
            else cv::cvtColor(view, view, cv::COLOR_BGR2RGB);
            std::vector<cv::Mat> ch;
            cv::split(view, ch);
            ch[0] *= s.redGain;
            ch[2] *= s.blueGain;
            cv::merge(ch, view);
            view.convertTo(out, CV_8UC3, 255);
        }
        for (int y = 0; y < s.height; ++y) std::memcpy(f.row(y), out.ptr(y), f.stride());
        f.metadata.exposureUs = s.exposureUs;
        f.metadata.analogueGain = s.analogueGain;
        f.metadata.redGain = s.redGain;
        f.metadata.blueGain = s.blueGain;
        f.metadata.sequence = sequence_++;
        f.metadata.timestampNs = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                     std::chrono::steady_clock::now().time_since_epoch()).count();
        f.metadata.stage = pos;
        return f;
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("sim camera: OpenCV: ") + e.what());
    }
}

} // namespace slicestation::sim
