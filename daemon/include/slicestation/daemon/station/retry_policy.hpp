#pragma once
/// The one retry policy for the station's devices (docs/architecture.md, "Retries"): every
/// move, capture and camera configuration of a section, in the scan loop and in autofocus
/// alike, gets 1 + retries attempts (ScanSettings::moveRetries for the stage,
/// captureRetries for the camera) while it fails with an error worth another attempt:
/// - never after Cancelled (stop() was asked: a cancel or a shutdown),
///   OutOfRange (nothing was done; the same request fails the same way) or
///   Alarm (the drive stopped itself; only a person clears it: resume with reset_stage_alarm);
/// - after anything else (Timeout, Disconnected, IoError, ...).
/// Before a capture is tried again the camera is re-initialised (stop(), then configure() with
/// the run's settings): a camera that timed out often needs it. Autofocus is not repeated as a
/// whole: its moves and captures already follow this policy.
///
/// Threading: plain functions on the devices' owning thread (the scan loop).
#include "slicestation/core/camera.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"

#include <chrono>
#include <optional>

namespace slicestation::daemon {

/// Whether a failed device call is worth another attempt (the rule above).
bool worthRetrying(const core::Error& error) noexcept;

/// moveTo with 1 + retries attempts under the policy. \return the settled position or the
/// last error.
[[nodiscard]] core::Result<hw::StagePosition> moveWithRetries(hw::Stage& stage,
                                                              const hw::StagePosition& target,
                                                              std::chrono::milliseconds timeout,
                                                              int retries);

/// configure with 1 + retries attempts under the policy. \return the settings the camera uses.
[[nodiscard]] core::Result<hw::CameraSettings>
configureWithRetries(hw::Camera& camera, const hw::CameraSettings& settings,
                     std::chrono::milliseconds timeout, int retries);

/// capture with 1 + retries attempts under the policy; before each retry the camera is
/// re-initialised with `reinitialise` when given (a failed re-initialisation counts as that
/// attempt's failure). \return the frame or the last error.
[[nodiscard]] core::Result<hw::Frame>
captureWithRetries(hw::Camera& camera, std::chrono::milliseconds timeout, int retries,
                   const std::optional<hw::CameraSettings>& reinitialise);

} // namespace slicestation::daemon
