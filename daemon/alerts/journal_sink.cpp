#include "slicestation/daemon/alerts/alert_channels.hpp"

#include "alert_util.hpp"

#include "slicestation/core/unique_fd.hpp"
#include "slicestation/daemon/config/config_document.hpp"

#include <httplib.h>
#include <systemd/sd-journal.h>

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <sys/uio.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <deque>
#include <initializer_list>
#include <map>
#include <optional>
#include <string_view>
#include <thread>

extern char** environ; // NOLINT(readability-redundant-declaration): POSIX declares it nowhere

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using Clock = std::chrono::steady_clock;

// Journal --------------------------------------------------------------------------------------

JournalSink::JournalSink(Send send) : send_(std::move(send)) {
    if (!send_)
        send_ = [](const std::vector<std::string>& fields) {
            std::vector<iovec> iov;
            iov.reserve(fields.size());
            for (const auto& f : fields)
                iov.push_back({const_cast<char*>(f.data()), f.size()});
            return sd_journal_sendv(iov.data(), static_cast<int>(iov.size()));
        };
}

std::vector<std::string> JournalSink::fields(const AlertRecord& alert) {
    std::vector<std::string> f{std::string("MESSAGE=ALERT ") + toString(alert.kind) + ": " +
                                   alert.message,
                               "PRIORITY=" + std::to_string(syslogPriority(alert.severity)),
                               "SYSLOG_IDENTIFIER=slicestationd",
                               "SLST_ALERT_ID=" + std::to_string(alert.id),
                               std::string("SLST_ALERT_KIND=") + toString(alert.kind),
                               std::string("SLST_ALERT_SEVERITY=") + toString(alert.severity)};
    if (alert.runId)
        f.push_back("SLST_RUN_ID=" + std::to_string(*alert.runId));
    if (alert.sectionId)
        f.push_back("SLST_SECTION_ID=" + std::to_string(*alert.sectionId));
    return f;
}

Result<void> JournalSink::deliver(const AlertRecord& alert) {
    const int rc = send_(fields(alert));
    if (rc < 0)
        return makeError(ErrorCode::IoError,
                         "journal: sd_journal_sendv: " + std::string(std::strerror(-rc)), -rc);
    return {};
}

Result<std::vector<std::unique_ptr<AlertChannelSink>>>
makeAlertSinks(const AlertSettings& settings, JournalSink::Send journalSend) {
    std::vector<std::unique_ptr<AlertChannelSink>> sinks;
    if (settings.journal)
        sinks.push_back(std::make_unique<JournalSink>(std::move(journalSend)));
    for (const auto& w : settings.webhooks) {
        auto sink = WebhookSink::create(w);
        if (!sink)
            return sink.error();
        sinks.push_back(std::move(*sink));
    }
    for (const auto& c : settings.commands) {
        auto sink = CommandSink::create(c);
        if (!sink)
            return sink.error();
        sinks.push_back(std::move(*sink));
    }
    return sinks;
}

} // namespace slicestation::daemon
