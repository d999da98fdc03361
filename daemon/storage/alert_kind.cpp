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

/// The enumerator whose text is `text` (enumerators are the texts' indices), or InvalidArgument
/// naming it and listing the known ones.
template <class Enum, std::size_t N>
core::Result<Enum> parseText(const char* const (&texts)[N], std::string_view text,
                             const char* what) {
    for (std::size_t i = 0; i < N; ++i)
        if (text == texts[i])
            return static_cast<Enum>(i);
    return core::makeError(core::ErrorCode::InvalidArgument,
                           std::string("unknown alert ") + what + " \"" + std::string(text) +
                               "\" (known: " + listOf(texts) + ")");
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
    return parseText<AlertKind>(kKindTexts, text, "kind");
}

core::Result<AlertSeverity> parseAlertSeverity(std::string_view text) {
    return parseText<AlertSeverity>(kSeverityTexts, text, "severity");
}

} // namespace slicestation::daemon
