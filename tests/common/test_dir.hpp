#pragma once
// Directories for tests that write real files: one per test (<tmp>/slst-<prefix>-<pid>-<test
// name>; the pid keeps parallel ctest processes apart, the test name the tests of one) or one per
// scope (mkdtemp). One helper for every such test, so that each does not carry its own copy of
// the naming and the clean-up.
#include <gtest/gtest.h>

#include <stdlib.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <string>
#include <system_error>

namespace slicestation::testing_dir {

/// `<tmp>/slst-<prefix>-<pid>-<name of the running test>`; nothing is created or removed.
inline std::filesystem::path perTestPath(const std::string& prefix) {
    return std::filesystem::temp_directory_path() /
           ("slst-" + prefix + "-" + std::to_string(::getpid()) + "-" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
}

/// perTestPath(prefix), emptied of what an earlier run left there and created.
inline std::filesystem::path freshTestDir(const std::string& prefix) {
    const auto dir = perTestPath(prefix);
    std::filesystem::remove_all(dir);
    std::filesystem::create_directories(dir);
    return dir;
}

/// A fixture whose every test gets an empty directory `dir_` (freshTestDir), removed after it.
/// A fixture that overrides SetUp or TearDown calls these first (SetUp) or last (TearDown).
class TempDirTest : public ::testing::Test {
protected:
    explicit TempDirTest(std::string prefix) : prefix_(std::move(prefix)) {}
    void SetUp() override { dir_ = freshTestDir(prefix_); }
    void TearDown() override {
        std::error_code ignored; // a test that fails half-way may leave what it cannot remove
        std::filesystem::remove_all(dir_, ignored);
    }

    std::filesystem::path dir_;

private:
    std::string prefix_;
};

/// A new directory <tmp>/slst-<prefix>-XXXXXX (mkdtemp) for as long as this lives; removed with
/// what it holds when it goes. A directory that cannot be made is a test failure (path() empty).
class ScratchDir {
public:
    explicit ScratchDir(const std::string& prefix) {
        std::string tmpl =
            (std::filesystem::temp_directory_path() / ("slst-" + prefix + "-XXXXXX")).string();
        if (const char* made = ::mkdtemp(tmpl.data()))
            path_ = made;
        else
            ADD_FAILURE() << "mkdtemp " << tmpl << ": " << std::strerror(errno);
    }
    ~ScratchDir() {
        std::error_code ec;
        if (!path_.empty())
            std::filesystem::remove_all(path_, ec);
    }
    ScratchDir(const ScratchDir&) = delete;
    ScratchDir& operator=(const ScratchDir&) = delete;
    const std::filesystem::path& path() const { return path_; }

private:
    std::filesystem::path path_;
};

} // namespace slicestation::testing_dir
