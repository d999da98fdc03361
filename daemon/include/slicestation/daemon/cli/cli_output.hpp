#pragma once
/// slicectl's output for people: tables, local times, numbers as people write them, a progress
/// line on a terminal, and the "did you mean" for a mistyped command. cli_output.cpp

#include <CLI/CLI.hpp>

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

namespace slicestation::daemon {

/// slicectl's exit codes (docs/operation.md).
enum ExitCode : int {
    kExitOk = 0,
    kExitUsage = 1,       ///< unknown command or option, missing argument
    kExitInput = 2,       ///< a value, file or record that is wrong or missing
    kExitUnreachable = 3, ///< the daemon (or a device) cannot be reached, or refused (401, 5xx)
    kExitConflict = 4,    ///< the request does not fit the state (HTTP 409: e.g. resume a run
                          ///< that is not paused)
};

/// A number as people write it: at most `digits` significant digits, no trailing zeros, no
/// exponent for ordinary magnitudes ("75000", "0.5", "12345.5").
std::string plainNumber(double value, int digits = 10);

/// A UTC time of the journal ("2026-12-02T09:30:00.000Z") in this machine's local time zone,
/// "2026-12-02 15:00:00"; empty for empty; the text itself when it is not such a time.
std::string localTime(const std::string& utc);
/// "local time, Asia/Kolkata (UTC+05:30)": the label printed with local times.
std::string localZoneLabel();

/// Left-aligned columns separated by two spaces, a header row, one line per row.
std::string formatTable(const std::vector<std::string>& header,
                        const std::vector<std::vector<std::string>>& rows);

/// The subcommand of `app` nearest to `word` (Damerau-free Levenshtein distance at most 2, or
/// `word` a prefix of it), or empty.
std::string nearestSubcommand(const CLI::App& app, const std::string& word);
/// For a failed parse: the first word of argv that names no subcommand where one was expected,
/// and the suggestion for it ("regster" -> "register"), as a "did you mean" sentence, or empty.
std::string didYouMean(const CLI::App& app, int argc, char** argv);

/// A progress line on stderr for long work, redrawn by a thread while it lives, only when
/// stderr is a terminal (otherwise silent): "slicectl atlas slice: cutting slices [#####   ]
/// 40/80  12.3 s", or a spinner with the elapsed time while the total is unknown. Erased when
/// destroyed. Thread-safe updates.
class Progress {
public:
    explicit Progress(std::string command);
    /// Forced on or off (tests); by default on when stderr is a terminal.
    Progress(std::string command, bool enabled);
    ~Progress();
    Progress(const Progress&) = delete;
    Progress& operator=(const Progress&) = delete;

    /// A new phase; total 0 when unknown (spinner).
    void phase(std::string name, int total = 0);
    void advance(int done);
    /// Also a new total (a total that becomes exact on the way), the phase kept.
    void advance(int done, int total);
    bool enabled() const noexcept { return enabled_; }
    /// The line as it is drawn now (without the carriage return).
    std::string line() const;

private:
    struct State;
    std::string command_;
    bool enabled_;
    std::shared_ptr<State> state_;
};

} // namespace slicestation::daemon
