#pragma once
/// slicectl camera --config FILE capture --output frame.tif [--x-um X --y-um Y [--z-um Z]]:
/// configures the station's camera with the [camera] settings, optionally moves the stage
/// first, captures one frame, writes it losslessly (TIFF or PNG, chosen by the extension) and
/// prints JSON (settings asked and used, frame metadata). Exit codes as cli.hpp.

#include "slicestation/daemon/cli/cli.hpp"

namespace slicestation::daemon {

CommandRunner addCameraCommand(CLI::App& app); ///< cli_camera.cpp

} // namespace slicestation::daemon
