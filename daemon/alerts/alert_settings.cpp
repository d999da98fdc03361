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

namespace {

/// Walks the [[alerts.<name>]] tables (absent: none): each must be a table with only `known`
/// keys, and `each(table, path)` reads it.
template <class Each>
Result<void> forEachTable(const nlohmann::json& alerts, const std::string& name,
                          std::initializer_list<std::string_view> known, const FieldReader& rd,
                          Each each) {
    if (!alerts.contains(name))
        return {};
    const auto& list = alerts[name];
    const std::string path = "alerts." + name;
    if (!list.is_array())
        return rd.bad(path, "expected [[" + path + "]] tables");
    for (std::size_t i = 0; i < list.size(); ++i) {
        const std::string p = path + "[" + std::to_string(i) + "]";
        const auto& e = list[i];
        if (!e.is_object())
            return rd.bad(p, "expected a table");
        if (auto keys = rd.onlyKeys(e, p, known); !keys)
            return keys.error();
        if (auto read = each(e, p); !read)
            return read.error();
    }
    return {};
}

/// `timeout_s` of a channel table, in milliseconds.
Result<std::chrono::milliseconds> timeoutOf(const nlohmann::json& e, const std::string& p,
                                            double fallback, const FieldReader& rd) {
    auto v = rd.number(e, p, "timeout_s", fallback, 0.01, 3600);
    if (!v)
        return v.error();
    return std::chrono::milliseconds(std::llround(*v * 1000));
}

/// One `[[alerts.webhook]]` table.
Result<WebhookSettings> readWebhook(const nlohmann::json& e, const std::string& p,
                                    const FieldReader& rd) {
    WebhookSettings w;
    auto url = rd.string(e, p, "url", std::nullopt);
    if (!url)
        return url.error();
    auto parsed = parseUrl(*url);
    if (!parsed)
        return rd.bad(p + ".url", parsed.error().message);
#ifndef CPPHTTPLIB_OPENSSL_SUPPORT
    if (parsed->scheme == "https")
        return rd.bad(p + ".url",
                      "https is not available: cpp-httplib was built without TLS; use http://");
#endif
    w.url = *url;
    auto format = rd.string(e, p, "format", std::string("json"));
    if (!format)
        return format.error();
    if (*format == "json")
        w.format = WebhookSettings::Format::Json;
    else if (*format == "slack")
        w.format = WebhookSettings::Format::Slack;
    else
        return rd.bad(p + ".format", "expected \"json\" or \"slack\", got \"" + *format + "\"");
    auto to = timeoutOf(e, p, 5, rd);
    if (!to)
        return to.error();
    w.timeout = *to;
    return w;
}

/// One `[[alerts.command]]` table.
Result<CommandSettings> readCommand(const nlohmann::json& e, const std::string& p,
                                    const FieldReader& rd) {
    CommandSettings c;
    if (!e.contains("argv"))
        return rd.bad(p + ".argv", "missing");
    const auto& argv = e["argv"];
    if (!argv.is_array() ||
        !std::all_of(argv.begin(), argv.end(), [](const auto& a) { return a.is_string(); }))
        return rd.bad(p + ".argv", "expected an array of strings, got " + argv.dump());
    if (argv.empty())
        return rd.bad(p + ".argv", "empty: name the program to run");
    for (const auto& a : argv)
        c.argv.push_back(a.get<std::string>());
    if (c.argv[0].empty())
        return rd.bad(p + ".argv", "the program name (argv[0]) is empty");
    auto to = timeoutOf(e, p, 10, rd);
    if (!to)
        return to.error();
    c.timeout = *to;
    return c;
}

} // namespace

// Settings -------------------------------------------------------------------------------------

Result<AlertSettings> parseAlertSettings(const nlohmann::json& station, const std::string& origin) {
    FieldReader rd(origin);
    AlertSettings s;
    if (!station.is_object() || !station.contains("alerts"))
        return s;
    const nlohmann::json& t = station["alerts"];
    if (!t.is_object())
        return rd.bad("alerts", "expected a table [alerts]");
    if (auto keys = rd.onlyKeys(t, "alerts",
                                {"journal", "retries", "backoff_initial_ms", "backoff_max_ms",
                                 "max_per_minute", "min_severity", "webhook", "command"});
        !keys)
        return keys.error();

    auto journal = rd.boolean(t, "alerts", "journal", true);
    if (!journal)
        return journal.error();
    s.journal = *journal;
    auto retries = rd.integer(t, "alerts", "retries", 4, 0, 100);
    if (!retries)
        return retries.error();
    s.retries = static_cast<int>(*retries);
    auto bi = rd.integer(t, "alerts", "backoff_initial_ms", 1000, 1, 3'600'000);
    if (!bi)
        return bi.error();
    s.backoffInitial = std::chrono::milliseconds(*bi);
    auto bm = rd.integer(t, "alerts", "backoff_max_ms", 60'000, 1, 86'400'000);
    if (!bm)
        return bm.error();
    if (*bm < *bi)
        return rd.bad("alerts.backoff_max_ms", "must not be less than backoff_initial_ms");
    s.backoffMax = std::chrono::milliseconds(*bm);
    auto mpm = rd.integer(t, "alerts", "max_per_minute", 20, 0, 100'000);
    if (!mpm)
        return mpm.error();
    s.maxPerWindow = static_cast<int>(*mpm);
    auto sev = rd.string(t, "alerts", "min_severity", std::string("info"));
    if (!sev)
        return sev.error();
    auto minSeverity = parseAlertSeverity(*sev);
    if (!minSeverity)
        return rd.bad("alerts.min_severity", minSeverity.error().message);
    s.minSeverity = *minSeverity;

    auto webhooks =
        forEachTable(t, "webhook", {"url", "format", "timeout_s"}, rd,
                     [&](const nlohmann::json& e, const std::string& p) -> Result<void> {
                         auto w = readWebhook(e, p, rd);
                         if (!w)
                             return w.error();
                         s.webhooks.push_back(std::move(*w));
                         return {};
                     });
    if (!webhooks)
        return webhooks.error();
    auto commands =
        forEachTable(t, "command", {"argv", "timeout_s"}, rd,
                     [&](const nlohmann::json& e, const std::string& p) -> Result<void> {
                         auto c = readCommand(e, p, rd);
                         if (!c)
                             return c.error();
                         s.commands.push_back(std::move(*c));
                         return {};
                     });
    if (!commands)
        return commands.error();
    return s;
}

} // namespace slicestation::daemon
