#pragma once
/// A simulated camera that looks at a virtual slide under the (simulated) stage.
///
/// The slide is an image with a known pixel size (µm/px) whose top-left corner is stage
/// position (slideOriginXUm, slideOriginYUm) (a VirtualSlide brings its own). Each capture
/// crops the field of view centred on the current stage X/Y (only the crop is resampled, at the
/// sensor pixel size; outside the slide image the edge glass continues), blurs it by the
/// distance of stage Z from a tilted focal surface (large blurs are computed at a reduced
/// resolution), scales brightness by exposure × gain (relative to the reference exposure) and
/// adds shot/read noise that grows with gain. A 1024 x 768 capture takes a few milliseconds.
/// Deterministic: noise is seeded by the frame sequence number.
/// Threading as hw::Camera; stop() has nothing to preempt (captures do not wait).

#include "slicestation/core/camera.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include <opencv2/core/mat.hpp>

#include <atomic>
#include <functional>
#include <memory>

namespace slicestation::sim {

struct SimCameraConfig {
    cv::Mat slide;             ///< CV_8UC1, CV_16UC1 or CV_8UC3 (BGR); tissue on glass
    double slideUmPerPx = 2.0; ///< pixel size of `slide`
    double slideOriginXUm = 0; ///< stage position of the slide image's top-left corner
    double slideOriginYUm = 0;
    double sensorUmPerPx = 2.0;                       ///< pixel size of the camera at the sample
    std::function<hw::StagePosition()> stagePosition; ///< where the stage is now (required)
    double focusZUm = 2'500; ///< focal surface: z = focusZUm + tiltX*x + tiltY*y
    double focusTiltX = 0.002, focusTiltY = -0.001;
    double blurSigmaPxPerUm = 0.15;            ///< Gaussian sigma per µm of defocus
    std::int64_t referenceExposureUs = 10'000; ///< exposure at which the slide's values show
};

/// A slide of `count` generated sections from the built-in atlas, side by side, each
/// `sectionSizePx` wide, at 2 µm/px on dark glass (fluorescence, 16-bit). Deterministic.
core::Result<cv::Mat> makeGeneratedSlide(int count, cv::Size sectionSizePx, std::uint64_t seed);

class SimCamera final : public hw::Camera {
public:
    /// InvalidArgument when the slide is empty or of another type, a pixel size is not positive,
    /// or stagePosition is missing.
    static core::Result<std::unique_ptr<SimCamera>> create(SimCameraConfig config);
    /// The same, looking at `slide` (its image, pixel size and origin replace config's).
    static core::Result<std::unique_ptr<SimCamera>> create(const VirtualSlide& slide,
                                                           SimCameraConfig config);

    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& settings,
                                               std::chrono::milliseconds timeout) override;
    core::Result<hw::Frame> capture(std::chrono::milliseconds timeout) override;
    void stop() noexcept override {}

private:
    explicit SimCamera(SimCameraConfig config) : config_(std::move(config)) {}
    SimCameraConfig config_;
    hw::CameraSettings settings_;
    std::uint64_t sequence_ = 0;
    struct Scratch {
        cv::Mat srcF, grid, view, noise, work;
    } scratch_;
};

} // namespace slicestation::sim
