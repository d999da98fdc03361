#pragma once
/// slicectl's subcommands. Each add*Command registers its options on `app` and returns a
/// runner that executes the command when the user chose it (returns the exit code).
/// Exit codes (ExitCode, cli_output.hpp; docs/operation.md): 0 success, 1 usage (unknown
/// command or option), 2 input error, 3 daemon or device unreachable or refused, 4 conflict.

#include "slicestation/core/result.hpp"

#include <CLI/CLI.hpp>

#include <functional>

namespace slicestation::daemon {

/// Runs the chosen command; returns -1 when this command was not the one chosen.
using CommandRunner = std::function<int()>;

CommandRunner addRegisterCommand(CLI::App& app);
CommandRunner addDemoCommand(CLI::App& app);
CommandRunner addCountCommand(CLI::App& app); ///< `count`: cells per region (count_command.cpp)
CommandRunner addStageCommand(CLI::App& app); ///< cli_stage.cpp
/// `atlas slice` and `atlas match` (atlas_command.hpp).
CommandRunner addAtlasCommands(CLI::App& app);
/// `atlas match-series` (atlas_series_command.cpp); after addAtlasCommands, run before it.
CommandRunner addAtlasSeriesCommand(CLI::App& app);
/// scan submit, status, runs, sections, section, pause, resume, cancel, rescan, alerts,
/// export: clients of a running slicestationd (cli_daemon.cpp).
CommandRunner addDaemonCommands(CLI::App& app);
/// `damage report` and `damage threshold [set X | clear]`: the lab's damage report and flag
/// score, through the daemon (damage_command.cpp; added by addDaemonCommands).
CommandRunner addDamageCommands(CLI::App& app);

/// A CLI11 check for a number option: finite and within [min, max]. CLI::Range and
/// CLI::PositiveNumber let "nan" through (every comparison with NaN is false).
CLI::Validator finiteRange(double min, double max);

/// Prints "slicectl <command>: error: <message>" on stderr and returns the exit code: 3 for a
/// device or daemon that cannot be reached or refuses (Disconnected, Timeout, Alarm, Cancelled),
/// else 2 (the input: a value, a file, a record).
int reportError(const char* command, const core::Error& error);

} // namespace slicestation::daemon
