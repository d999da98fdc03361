#include "slicestation/daemon/storage/alert_kind.hpp"

namespace slicestation::daemon {

namespace {

#define SLST_ALERT_KIND_TEXT(name, text) text,
constexpr const char* kKindTexts[] = {SLST_ALERT_KINDS(SLST_ALERT_KIND_TEXT)};
#undef SLST_ALERT_KIND_TEXT
constexpr const char* kSeverityTexts[] = {"info", "warning", "critical"};

template <std::size_t N> std::string listOf(const char* const (&texts)[N]) {
    std::string out;
    for (const char* t : texts)
        out += (out.empty() ? "" : ", ") + std::string(t);
    return out;
}

} // namespace

static_assert(std::size(kKindTexts) == std::size(kAlertKinds));

const char* toString(AlertKind kind) noexcept {
    const auto i = static_cast<std::size_t>(kind);
    return i < std::size(kKindTexts) ? kKindTexts[i] : "unknown";
}

const char* toString(AlertSeverity severity) noexcept {
    const auto i = static_cast<std::size_t>(severity);
    return i < std::size(kSeverityTexts) ? kSeverityTexts[i] : "unknown";
}

int syslogPriority(AlertSeverity severity) noexcept {
    switch (severity) {
    case AlertSeverity::Info:
        return 5;
    case AlertSeverity::Warning:
        return 4;
    case AlertSeverity::Critical:
        break;
    }
    return 2;
}

core::Result<AlertKind> parseAlertKind(std::string_view text) {
    for (std::size_t i = 0; i < std::size(kKindTexts); ++i)
        if (text == kKindTexts[i])
            return static_cast<AlertKind>(i);
    return core::makeError(core::ErrorCode::InvalidArgument,
                           "unknown alert kind \"" + std::string(text) +
                               "\" (known: " + listOf(kKindTexts) + ")");
}

core::Result<AlertSeverity> parseAlertSeverity(std::string_view text) {
    for (std::size_t i = 0; i < std::size(kSeverityTexts); ++i)
        if (text == kSeverityTexts[i])
            return static_cast<AlertSeverity>(i);
    return core::makeError(core::ErrorCode::InvalidArgument,
                           "unknown alert severity \"" + std::string(text) +
                               "\" (known: " + listOf(kSeverityTexts) + ")");
}

} // namespace slicestation::daemon
