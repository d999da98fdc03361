#include "slicestation/core/result.hpp"

namespace slicestation::core {

std::string_view toString(ErrorCode code) noexcept {
    switch (code) {
    case ErrorCode::InvalidArgument:
        return "invalid_argument";
    case ErrorCode::NotFound:
        return "not_found";
    case ErrorCode::IoError:
        return "io_error";
    case ErrorCode::Unsupported:
        return "unsupported";
    case ErrorCode::NoTissue:
        return "no_tissue";
    case ErrorCode::Timeout:
        return "timeout";
    case ErrorCode::Disconnected:
        return "disconnected";
    case ErrorCode::Alarm:
        return "alarm";
    case ErrorCode::OutOfRange:
        return "out_of_range";
    case ErrorCode::Cancelled:
        return "cancelled";
    case ErrorCode::Internal:
        return "internal";
    }
    return "unknown";
}

} // namespace slicestation::core
