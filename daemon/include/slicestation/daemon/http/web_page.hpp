#pragma once
/// The station's web page (daemon/http/web/index.html), embedded in the binary at build time so the
/// daemon serves it at GET / with no files to install and no external resources.
#include <string_view>

namespace slicestation::daemon {

/// The page, HTML with its style and script inline.
std::string_view webPage() noexcept;

} // namespace slicestation::daemon
