#pragma once
/// Errors as values: a small subset of C++23 std::expected.
/// Expected failures are returned as Result<T>; bugs are assertions. Switch to std::expected
/// once the toolchain has C++23.

#include <cassert>
#include <string>
#include <string_view>
#include <utility>
#include <variant>

namespace slicestation::core {

/// The closed set of error kinds callers branch on (retry, degrade, stop).
enum class ErrorCode {
    InvalidArgument, ///< bad input from outside: config, CLI option, CSV, request
    NotFound,        ///< a file, device or record that does not exist
    IoError,         ///< read/write failed or data is corrupt/truncated
    Unsupported,     ///< a valid but unsupported format or feature
    NoTissue,        ///< an image holds no tissue to work on
    Timeout,         ///< a deadline passed
    Disconnected,    ///< the device went away
    Alarm,           ///< the device reports an alarm
    OutOfRange,      ///< a request outside limits; nothing was done
    Cancelled,       ///< stop() preempted the call; the device was told to halt
    Internal,        ///< a third-party library failed unexpectedly
};

/// Stable lower-case name of a code, for messages and JSON.
std::string_view toString(ErrorCode code) noexcept;

struct Error {
    ErrorCode code = ErrorCode::Internal;
    std::string message; ///< names the file, field, device or register concerned
    int sysErrno = 0;    ///< errno when a system call failed, else 0
};

inline Error makeError(ErrorCode code, std::string message, int sysErrno = 0) {
    return Error{code, std::move(message), sysErrno};
}

template <class T> class [[nodiscard]] Result {
public:
    Result(T value) : v_(std::move(value)) {}     // NOLINT(google-explicit-constructor)
    Result(Error error) : v_(std::move(error)) {} // NOLINT(google-explicit-constructor)

    bool ok() const noexcept { return v_.index() == 0; }
    explicit operator bool() const noexcept { return ok(); }

    T& value() & {
        assert(ok());
        return std::get<0>(v_);
    }
    const T& value() const& {
        assert(ok());
        return std::get<0>(v_);
    }
    T&& value() && {
        assert(ok());
        return std::get<0>(std::move(v_));
    }
    T& operator*() & { return value(); }
    const T& operator*() const& { return value(); }
    T* operator->() { return &value(); }
    const T* operator->() const { return &value(); }

    const Error& error() const {
        assert(!ok());
        return std::get<1>(v_);
    }

private:
    std::variant<T, Error> v_;
};

template <> class [[nodiscard]] Result<void> {
public:
    Result() = default;
    Result(Error error) : error_(std::move(error)), ok_(false) {} // NOLINT
    bool ok() const noexcept { return ok_; }
    explicit operator bool() const noexcept { return ok_; }
    const Error& error() const {
        assert(!ok_);
        return error_;
    }

private:
    Error error_;
    bool ok_ = true;
};

} // namespace slicestation::core
