// slicectl: the station's command-line tool. Each subcommand lives in its own cli_*.cpp.
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_camera.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/version.hpp"

#include <iostream>
#include <vector>

int main(int argc, char** argv) {
    using namespace slicestation::daemon;
    CLI::App app{"slicestation: image brain sections and register them to an annotated atlas"};
    app.set_version_flag("--version", std::string("slicectl ") + kVersion);
    app.require_subcommand(1);
    std::vector<CommandRunner> commands;
    commands.push_back(addRegisterCommand(app));
    commands.push_back(addDemoCommand(app));
    commands.push_back(addCountCommand(app));
    commands.push_back(addStageCommand(app));
    commands.push_back(addCameraCommand(app));
    commands.push_back(addAtlasCommands(app));
    commands.insert(commands.begin(), addAtlasSeriesCommand(app));
    commands.push_back(addDaemonCommands(app));

    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        // --help and --version end here with 0. A value that fails its check or conversion is
        // an input error (2); anything else (unknown command or option, a missing argument) is
        // a usage error (1), with a suggestion for a mistyped command.
        const std::string hint = didYouMean(app, argc, argv);
        if (!hint.empty() && e.get_exit_code() != 0) {
            std::cerr << "slicectl: " << hint << "\n";
            return kExitUsage;
        }
        if (app.exit(e) == 0)
            return kExitOk;
        if (dynamic_cast<const CLI::ValidationError*>(&e) ||
            dynamic_cast<const CLI::ConversionError*>(&e))
            return kExitInput;
        return kExitUsage;
    }
    for (const auto& run : commands)
        if (const int rc = run(); rc >= 0)
            return rc;
    return kExitOk;
}
