#include "slicestation/core/result.hpp"

#include <gtest/gtest.h>

#include <memory>
#include <set>
#include <string>

namespace slicestation::core {
namespace {

Result<int> half(int value) {
    if (value % 2 != 0) {
        return makeError(ErrorCode::InvalidArgument, "odd value " + std::to_string(value), 22);
    }
    return value / 2;
}

Result<void> check(bool good) {
    if (!good) {
        return makeError(ErrorCode::IoError, "check failed");
    }
    return {};
}

TEST(Result, HoldsValueWhenOk) {
    const Result<int> r = half(84);
    ASSERT_TRUE(r.ok());
    EXPECT_TRUE(static_cast<bool>(r));
    EXPECT_EQ(r.value(), 42);
    EXPECT_EQ(*r, 42);
}

TEST(Result, HoldsErrorWhenFailed) {
    const Result<int> r = half(7);
    ASSERT_FALSE(r.ok());
    EXPECT_FALSE(static_cast<bool>(r));
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    EXPECT_EQ(r.error().message, "odd value 7");
    EXPECT_EQ(r.error().sysErrno, 22);
}

TEST(Result, MovesMoveOnlyValuesOut) {
    Result<std::unique_ptr<std::string>> r = std::make_unique<std::string>("slice");
    ASSERT_TRUE(r.ok());
    EXPECT_EQ(r->get()->size(), 5u);
    std::unique_ptr<std::string> taken = std::move(r).value();
    ASSERT_NE(taken, nullptr);
    EXPECT_EQ(*taken, "slice");
}

TEST(Result, VoidResultIsOkByDefaultAndCarriesErrors) {
    const Result<void> good = check(true);
    EXPECT_TRUE(good.ok());
    const Result<void> bad = check(false);
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().code, ErrorCode::IoError);
    EXPECT_EQ(bad.error().message, "check failed");
    EXPECT_EQ(bad.error().sysErrno, 0);
}

TEST(Result, ErrorCodeNamesAreStableAndDistinct) {
    EXPECT_EQ(toString(ErrorCode::NotFound), "not_found");
    EXPECT_EQ(toString(ErrorCode::IoError), "io_error");
    EXPECT_EQ(toString(ErrorCode::InvalidArgument), "invalid_argument");
    std::set<std::string_view> names;
    for (ErrorCode code :
         {ErrorCode::InvalidArgument, ErrorCode::NotFound, ErrorCode::IoError,
          ErrorCode::Unsupported, ErrorCode::NoTissue, ErrorCode::Timeout, ErrorCode::Disconnected,
          ErrorCode::Alarm, ErrorCode::OutOfRange, ErrorCode::Internal}) {
        EXPECT_NE(toString(code), "unknown");
        names.insert(toString(code));
    }
    EXPECT_EQ(names.size(), 10u);
}

} // namespace
} // namespace slicestation::core
