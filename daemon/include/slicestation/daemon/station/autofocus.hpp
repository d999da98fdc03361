#pragma once
/// Autofocus: a coarse-to-fine Z search on a focus measure, run only where there is tissue,
/// and a per-slide focus surface that predicts where to start.
///
/// Threading: the functions are re-entrant; autofocus() drives the stage and camera it is given
/// and so runs on their owning thread. FocusSurface is a plain value (not synchronised).

#include "slicestation/core/camera.hpp"
#include "slicestation/core/frame.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"

#include <opencv2/core/mat.hpp>

#include <chrono>
#include <cstddef>
#include <optional>
#include <vector>

namespace slicestation::daemon {

/// The focus and tissue measures are pipeline::focusMeasure and pipeline::tissueFraction
/// (pipeline/focus_measures.hpp).

struct AutofocusSettings {
    double rangeUm = 150; ///< full width of the search, centred on the start z
    double coarseStepUm = 25;
    double fineStepUm = 5;
    double minTissueFraction = 0.03; ///< below this at the start z: blank glass, no search
    std::chrono::milliseconds moveTimeout{10'000};   ///< per move
    std::chrono::milliseconds captureTimeout{5'000}; ///< per capture
    /// Extra attempts of a move and of a capture, under the station's one retry policy
    /// (retry_policy.hpp: never after Cancelled, OutOfRange or Alarm).
    int moveRetries = 0;
    int captureRetries = 0;
    /// The run's camera settings: the camera is re-initialised with them before a capture is
    /// tried again. None: a capture is simply tried again.
    std::optional<hw::CameraSettings> camera;
};

struct FocusResult {
    double zUm = 0;   ///< best z found (the start z when no tissue)
    double score = 0; ///< focusMeasure at zUm
    int captures = 0; ///< frames taken
    bool tissueFound = false;
    double tissueFraction = 0; ///< at the start z
    /// The best coarse z was at the edge of the range (clamped by the stage limits or the
    /// range): focus may lie beyond it. The result is still the best z seen.
    bool peakAtRangeEdge = false;
};

/// Which part failed when autofocus() returns an error: the stage (a move: Timeout after the
/// retries, Alarm, Disconnected, Cancelled), the camera (a capture), or the focus search itself
/// (settings, no Z axis, a library failure).
enum class FocusFailure { Focus, Stage, Camera };

/// Moves to `at` (x, y and start z), captures, and returns at once with tissueFound=false and
/// zUm=at.zUm when the field holds less tissue than minTissueFraction (never focuses on blank
/// glass). Otherwise: a coarse sweep over [z - range/2, z + range/2] (clamped to the stage's Z
/// limits) in coarseStep, then a fine sweep of +/- one coarse step around the best in fineStep,
/// each sweep approached from below (same direction, so backlash is the same for every frame);
/// the result is the best fine z. The stage is left at that z, approached from below.
///
/// Blocking: every move and capture with its own timeout from `s`.
/// \return the result; InvalidArgument (steps not > 0, fineStep > coarseStep, range < coarse
///         step, minTissueFraction outside [0, 1], the stage has no Z axis); errors of the stage
///         and camera are returned unchanged (Timeout, Alarm, Disconnected, Cancelled, ...).
///         On an error, `*failed` (when given) says which device failed.
[[nodiscard]] core::Result<FocusResult> autofocus(hw::Stage& stage, hw::Camera& camera,
                                                  const hw::StagePosition& at,
                                                  const AutofocusSettings& s,
                                                  FocusFailure* failed = nullptr);

/// Focus heights measured on one slide, and the height predicted elsewhere.
/// Prediction: with 0 points nullopt; with 1 point, or points all at the same x/y, their mean;
/// with points on one line, a least-squares line along it (sections in a row); otherwise the
/// least-squares plane z = a + b x + c y.
class FocusSurface {
public:
    void add(double xUm, double yUm, double zUm);
    std::optional<double> predict(double xUm, double yUm) const;
    std::size_t size() const noexcept { return points_.size(); }
    void clear() noexcept { points_.clear(); }

private:
    struct Point {
        double x, y, z;
    };
    std::vector<Point> points_;
};

} // namespace slicestation::daemon
