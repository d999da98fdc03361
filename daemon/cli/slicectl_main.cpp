// slicectl: the station's command-line tool. Each subcommand lives in its own cli_*.cpp.
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_camera.hpp"

#include <vector>

int main(int argc, char** argv) {
    using namespace slicestation::daemon;
    CLI::App app{"slicestation: image brain sections and register them to an annotated atlas"};
    app.require_subcommand(1);
    std::vector<CommandRunner> commands;
    commands.push_back(addRegisterCommand(app));
    commands.push_back(addDemoCommand(app));
    commands.push_back(addStageCommand(app));
    commands.push_back(addCameraCommand(app));
    commands.push_back(addAtlasCommands(app));
    commands.insert(commands.begin(), addAtlasSeriesCommand(app));
    commands.push_back(addDaemonCommands(app));

    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        // CLI11 prints the problem; a usage error is invalid input: exit 2 (cli.hpp), not
        // CLI11's own codes (105 for a failed check), so scripts see one code for bad input.
        return app.exit(e) == 0 ? 0 : 2;
    }
    for (const auto& run : commands)
        if (const int rc = run(); rc >= 0)
            return rc;
    return 0;
}
