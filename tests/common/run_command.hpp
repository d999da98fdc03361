#pragma once
// Running a program of the build from a test (slicectl end to end): one helper for every test
// that needs it, so that each does not carry its own copy of the popen loop.
#include <array>
#include <cstdio>
#include <string>
#include <sys/wait.h>

namespace slicestation::testing_cli {

struct CommandResult {
    int exitCode = -1;  ///< the exit status, or -1 when the program did not exit normally
    std::string output; ///< what it printed (stderr too when the command line redirects it)
};

/// Runs `commandLine` through the shell and collects its standard output.
inline CommandResult runCommand(const std::string& commandLine) {
    CommandResult r;
    FILE* p = ::popen(commandLine.c_str(), "r");
    std::array<char, 4096> buf{};
    while (p && std::fgets(buf.data(), buf.size(), p))
        r.output += buf.data();
    const int status = p ? ::pclose(p) : -1;
    r.exitCode = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    return r;
}

#ifdef SLICECTL_PATH
/// `slicectl ARGS` of this build, stdout and stderr together.
inline CommandResult slicectl(const std::string& args) {
    return runCommand(std::string(SLICECTL_PATH) + " " + args + " 2>&1");
}
#endif

} // namespace slicestation::testing_cli
