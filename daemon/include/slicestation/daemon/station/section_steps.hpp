#pragma once
/// The steps of one section, each a function of its own (docs/architecture.md, "One section's
/// path"): check the disk, move to the section, autofocus, capture (one field, or tiles
/// stitched), write the OME-TIFF. The scan loop (scanner.hpp) calls them in order and journals
/// the capture; a step that fails returns a Fault (the alert kind and the error), and the loop
/// pauses the run with it. Device calls follow the one retry policy (retry_policy.hpp).
///
/// Threading: the devices' owning thread (the scan loop). Holds references only.
#include "slicestation/core/camera.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/autofocus.hpp"
#include "slicestation/daemon/station/phase_stats.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <variant>

namespace slicestation::daemon {

class ProgressWatchdog;

/// Why a section could not be captured: the alert kind (stage_fault, camera_fault, focus_fault,
/// low_disk, storage_fault, journal_error) and the error.
struct Fault {
    AlertKind kind;
    core::Error error;
};

/// A step's value, or its Fault.
template <class T> class Step {
public:
    Step(T value) : v_(std::move(value)) {}     // NOLINT(google-explicit-constructor)
    Step(Fault fault) : v_(std::move(fault)) {} // NOLINT(google-explicit-constructor)
    explicit operator bool() const noexcept { return v_.index() == 0; }
    T& operator*() { return std::get<0>(v_); }
    T* operator->() { return &std::get<0>(v_); }
    const Fault& fault() const { return std::get<1>(v_); }

private:
    std::variant<T, Fault> v_;
};

/// Where a capture's image goes, relative to the state directory:
///   runs/<run id>/<slide number, 2+ digits>-<slide name>/<section id>-<section
///   name>-a<attempt>.ome.tif
/// The run id, slide number (index + 1 within the run) and section id (unique in the journal)
/// make it injective whatever the names; the names (ASCII letters, digits, '-' and '_' kept,
/// every other byte '_', at most 48 bytes) are only there for people.
std::filesystem::path imagePathFor(const RunRecord& run, const SectionRecord& section, int attempt);

class SectionSteps {
public:
    struct Deps {
        hw::Stage& stage;
        hw::Camera& camera;
        PhaseStats& stats;
        std::filesystem::path stateDir;
        /// Free bytes where images are written; null: not checked.
        std::function<core::Result<std::uint64_t>(const std::filesystem::path&)> freeSpace;
        ProgressWatchdog* watchdog = nullptr; ///< told of progress; may be null
    };
    SectionSteps(Deps deps, const ScanSettings& settings) : d_(std::move(deps)), s_(settings) {}

    /// The run's camera settings applied (retry policy); the field of view follows from what
    /// the camera reports. Fault: camera_fault.
    Step<hw::CameraSettings> configureCamera();
    /// Field of view in stage micrometres (after configureCamera()).
    double fieldWidthUm() const { return fieldWUm_; }
    double fieldHeightUm() const { return fieldHUm_; }

    /// Never start a section that cannot be stored. nullopt: enough space; else low_disk (below
    /// the threshold) or storage_fault (the free space cannot be read).
    std::optional<Fault> checkDisk() const;
    /// Moves (retry policy; z dropped on a stage without Z). Fault: stage_fault.
    Step<hw::StagePosition> move(hw::StagePosition target);

    struct Focus {
        double zUm = 0;
        bool found = false; ///< tissue found and focused
        std::optional<double> score;
    };
    /// Autofocus at (x, y) from `zUm` when the run asks for it and the stage has Z; else `zUm`
    /// unchanged. Faults: stage_fault or camera_fault (the device that failed during the
    /// sweep), focus_fault (the search itself).
    Step<Focus> focus(double xUm, double yUm, double zUm);

    struct Capture {
        cv::Mat image;           ///< in the stage frame (camera orientation applied)
        hw::StagePosition stage; ///< the section centre (the settled one for one field)
        hw::FrameMetadata meta;  ///< of the last frame
        int tiles = 0;
    };
    /// One field, or tiles covering the section stitched by stage position. `activity` is told
    /// when stitching starts. Faults: stage_fault (a tile's move), camera_fault (a capture or
    /// the stitch).
    Step<Capture> capture(const SectionRecord& section, double zUm,
                          const std::function<void(const std::string&)>& activity);

    /// Writes the OME-TIFF to stateDir/rel atomically. A file already there that no capture
    /// refers to (a crash came between writing and journaling) is replaced; one a capture
    /// refers to never is. Faults: storage_fault, low_disk (ENOSPC), journal_error.
    std::optional<Fault> writeImage(const std::filesystem::path& rel, const Capture& capture,
                                    const std::string& name, const hw::CameraSettings& used,
                                    Journal& journal);

private:
    Deps d_;
    const ScanSettings& s_;
    double fieldWUm_ = 0, fieldHUm_ = 0;
};

} // namespace slicestation::daemon
