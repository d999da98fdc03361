// slicectl's output for people: tables, local times, plain numbers, progress, "did you mean".
#include "slicestation/daemon/cli/cli_output.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <ctime>
#include <iostream>
#include <mutex>
#include <sstream>
#include <thread>

namespace slicestation::daemon {

std::string plainNumber(double value, int digits) {
    if (!std::isfinite(value))
        return std::isnan(value) ? "nan" : (value < 0 ? "-inf" : "inf");
    std::ostringstream os;
    os.precision(digits);
    os << std::defaultfloat << value;
    std::string s = os.str();
    // Large magnitudes come out with an exponent from %g: write them out.
    if (s.find('e') != std::string::npos && std::fabs(value) >= 1 && std::fabs(value) < 1e15) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "%.0f", value);
        s = buf;
    }
    return s == "-0" ? "0" : s;
}

std::string localTime(const std::string& utc) {
    if (utc.empty())
        return {};
    std::tm tm{};
    int y = 0, mo = 0, d = 0, h = 0, mi = 0, sec = 0;
    if (std::sscanf(utc.c_str(), "%4d-%2d-%2dT%2d:%2d:%2d", &y, &mo, &d, &h, &mi, &sec) != 6)
        return utc;
    tm.tm_year = y - 1900;
    tm.tm_mon = mo - 1;
    tm.tm_mday = d;
    tm.tm_hour = h;
    tm.tm_min = mi;
    tm.tm_sec = sec;
    const std::time_t t = ::timegm(&tm);
    std::tm local{};
    if (t == static_cast<std::time_t>(-1) || !::localtime_r(&t, &local))
        return utc;
    char buf[32];
    std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", &local);
    return buf;
}

std::string localZoneLabel() {
    const std::time_t now = std::time(nullptr);
    std::tm local{};
    ::localtime_r(&now, &local);
    const long off = local.tm_gmtoff / 60;
    char buf[96];
    std::snprintf(buf, sizeof buf, "local time, %s (UTC%c%02ld:%02ld)",
                  local.tm_zone ? local.tm_zone : "local", off < 0 ? '-' : '+', std::labs(off) / 60,
                  std::labs(off) % 60);
    return buf;
}

std::string formatTable(const std::vector<std::string>& header,
                        const std::vector<std::vector<std::string>>& rows) {
    std::vector<std::size_t> width(header.size(), 0);
    auto measure = [&](const std::vector<std::string>& row) {
        for (std::size_t i = 0; i < row.size() && i < width.size(); ++i)
            width[i] = std::max(width[i], row[i].size());
    };
    measure(header);
    for (const auto& r : rows)
        measure(r);
    std::string out;
    auto line = [&](const std::vector<std::string>& row) {
        std::string l;
        for (std::size_t i = 0; i < width.size(); ++i) {
            const std::string cell = i < row.size() ? row[i] : "";
            l += cell;
            if (i + 1 < width.size())
                l += std::string(width[i] - cell.size() + 2, ' ');
        }
        while (!l.empty() && l.back() == ' ')
            l.pop_back();
        out += l + "\n";
    };
    line(header);
    for (const auto& r : rows)
        line(r);
    return out;
}

namespace {
std::size_t editDistance(const std::string& a, const std::string& b) {
    std::vector<std::size_t> prev(b.size() + 1), cur(b.size() + 1);
    for (std::size_t j = 0; j <= b.size(); ++j)
        prev[j] = j;
    for (std::size_t i = 1; i <= a.size(); ++i) {
        cur[0] = i;
        for (std::size_t j = 1; j <= b.size(); ++j)
            cur[j] = std::min(
                {prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (a[i - 1] == b[j - 1] ? 0u : 1u)});
        std::swap(prev, cur);
    }
    return prev[b.size()];
}
} // namespace

std::string nearestSubcommand(const CLI::App& app, const std::string& word) {
    std::string best;
    std::size_t bestDistance = 3;
    for (const CLI::App* sub : app.get_subcommands([](const CLI::App*) { return true; })) {
        const std::string& name = sub->get_name();
        std::size_t d = editDistance(word, name);
        if (word.size() >= 3 && name.starts_with(word))
            d = std::min<std::size_t>(d, 1);
        if (d < bestDistance) {
            bestDistance = d;
            best = name;
        }
    }
    return best;
}

std::string didYouMean(const CLI::App& app, int argc, char** argv) {
    const CLI::App* cur = &app;
    std::string path;
    for (int i = 1; i < argc; ++i) {
        const std::string arg = argv[i];
        if (arg.empty() || arg[0] == '-')
            return {}; // options come after the command words
        const auto subs = cur->get_subcommands([](const CLI::App*) { return true; });
        if (subs.empty())
            return {};
        const auto it = std::find_if(subs.begin(), subs.end(),
                                     [&](const CLI::App* s) { return s->get_name() == arg; });
        if (it != subs.end()) {
            cur = *it;
            path += arg + " ";
            continue;
        }
        const std::string near = nearestSubcommand(*cur, arg);
        if (near.empty())
            return "unknown command \"" + path + arg + "\"; see slicectl " + path + "--help";
        return "unknown command \"" + path + arg + "\"; did you mean \"" + path + near + "\"?";
    }
    return {};
}

struct Progress::State {
    mutable std::mutex mutex;
    std::condition_variable cv;
    std::string phase;
    int done = 0, total = 0;
    bool stop = false;
    std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now();
    std::thread drawer;
    std::size_t drawn = 0; ///< length of the last line drawn
};

Progress::Progress(std::string command) : Progress(std::move(command), ::isatty(STDERR_FILENO)) {}

Progress::Progress(std::string command, bool enabled)
    : command_(std::move(command)), enabled_(enabled), state_(std::make_shared<State>()) {
    if (!enabled_)
        return;
    state_->drawer = std::thread([this] {
        std::unique_lock lock(state_->mutex);
        while (!state_->stop) {
            lock.unlock();
            const std::string l = line();
            lock.lock();
            const std::size_t pad = state_->drawn > l.size() ? state_->drawn - l.size() : 0;
            std::cerr << "\r" << l << std::string(pad, ' ') << std::flush;
            state_->drawn = l.size();
            state_->cv.wait_for(lock, std::chrono::milliseconds(200));
        }
    });
}

Progress::~Progress() {
    if (!enabled_)
        return;
    {
        std::lock_guard lock(state_->mutex);
        state_->stop = true;
    }
    state_->cv.notify_all();
    state_->drawer.join();
    std::cerr << "\r" << std::string(state_->drawn, ' ') << "\r" << std::flush;
}

void Progress::phase(std::string name, int total) {
    std::lock_guard lock(state_->mutex);
    state_->phase = std::move(name);
    state_->total = std::max(total, 0);
    state_->done = 0;
}

void Progress::advance(int done) {
    std::lock_guard lock(state_->mutex);
    state_->done = std::clamp(done, 0, std::max(state_->total, 0));
}

void Progress::advance(int done, int total) {
    std::lock_guard lock(state_->mutex);
    state_->total = std::max(total, 0);
    state_->done = std::clamp(done, 0, state_->total);
}

std::string Progress::line() const {
    std::lock_guard lock(state_->mutex);
    const double s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - state_->start).count();
    char secs[32];
    std::snprintf(secs, sizeof secs, "%.1f s", s);
    std::string l = "slicectl " + command_ + ": " + state_->phase + " ";
    if (state_->total > 0) {
        constexpr int kWidth = 24;
        const int filled = state_->done * kWidth / state_->total;
        l += "[" + std::string(static_cast<std::size_t>(filled), '#') +
             std::string(static_cast<std::size_t>(kWidth - filled), ' ') + "] " +
             std::to_string(state_->done) + "/" + std::to_string(state_->total) + "  ";
    } else {
        static constexpr const char* kSpin = "|/-\\";
        l += std::string(1, kSpin[static_cast<int>(s * 5) % 4]) + "  ";
    }
    return l + secs;
}

} // namespace slicestation::daemon
