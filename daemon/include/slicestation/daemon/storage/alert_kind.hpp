#pragma once
/// The alert vocabulary: what happened (AlertKind) and how bad it is (AlertSeverity). The journal,
/// the JSON API, the channels and the environment of an alert command carry them as the strings
/// below, unchanged since they were free text (compatibility); parsing refuses anything else with
/// an error naming it, so an unknown severity is never taken for "critical" or "info".
#include "slicestation/core/result.hpp"

#include <array>
#include <string>
#include <string_view>

namespace slicestation::daemon {

// Every kind the daemon raises, as X(Enumerator, "text"). A new kind is one line here.
#define SLST_ALERT_KINDS(X)                                                                        \
    X(Damaged, "damaged")                      /* registration found a damaged section */          \
    X(CheckRegistration, "check_registration") /* tissue missing where the atlas fit is unsure */  \
    X(AtlasMismatch, "atlas_mismatch")         /* the section matches another atlas slice */       \
    X(RegistrationFailed, "registration_failed") /* registration could not run or finish */        \
    X(StageFault, "stage_fault")                 /* a move failed; the run pauses */               \
    X(CameraFault, "camera_fault")               /* a capture or stitch failed */                  \
    X(FocusFault, "focus_fault")                 /* autofocus found no focus */                    \
    X(StorageFault, "storage_fault")             /* an image or file could not be written */       \
    X(LowDisk, "low_disk")                       /* the disk is (nearly) full */                   \
    X(JournalError, "journal_error")             /* the journal refused a write */                 \
    X(RunFinished, "run_finished")                                                                 \
    X(RunPaused, "run_paused")                                                                     \
    X(RunFailed, "run_failed")                                                                     \
    X(RunCancelled, "run_cancelled")                                                               \
    X(Restarted, "restarted")        /* the daemon was not stopped cleanly */                      \
    X(AlertSummary, "alert_summary") /* a channel's rate limit held alerts back */

enum class AlertKind {
#define SLST_ALERT_KIND_ENUMERATOR(name, text) name,
    SLST_ALERT_KINDS(SLST_ALERT_KIND_ENUMERATOR)
#undef SLST_ALERT_KIND_ENUMERATOR
};

/// Every kind, in declaration order (for tests and documentation).
#define SLST_ALERT_KIND_VALUE(name, text) AlertKind::name,
inline constexpr AlertKind kAlertKinds[] = {SLST_ALERT_KINDS(SLST_ALERT_KIND_VALUE)};
#undef SLST_ALERT_KIND_VALUE

/// Lowest first: the order is the rank (minimum severities compare with <).
enum class AlertSeverity { Info, Warning, Critical };

inline constexpr std::array<AlertSeverity, 3> kAlertSeverities = {
    AlertSeverity::Info, AlertSeverity::Warning, AlertSeverity::Critical};

/// The stored text ("damaged", "low_disk", ...).
const char* toString(AlertKind kind) noexcept;
/// "info", "warning" or "critical".
const char* toString(AlertSeverity severity) noexcept;
/// The syslog priority a severity is logged at: 5 notice, 4 warning, 2 critical.
int syslogPriority(AlertSeverity severity) noexcept;
/// InvalidArgument naming `text` and listing the known kinds.
[[nodiscard]] core::Result<AlertKind> parseAlertKind(std::string_view text);
/// InvalidArgument naming `text` and listing info, warning, critical.
[[nodiscard]] core::Result<AlertSeverity> parseAlertSeverity(std::string_view text);

} // namespace slicestation::daemon
