// The one atomic-replace helper every writer goes through: content, no leftovers, the
// no-replace mode, errors, and the temporary names the crash clean-up recognises.
#include "slicestation/core/atomic_file.hpp"

#include "../common/test_dir.hpp"

#include <gtest/gtest.h>

#include <unistd.h>

#include <cerrno>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace slicestation::test {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;

class AtomicFile : public testing_dir::TempDirTest {
protected:
    AtomicFile() : TempDirTest("atomic") {}
    std::vector<std::string> names() const {
        std::vector<std::string> out;
        for (const auto& e : fs::directory_iterator(dir_))
            out.push_back(e.path().filename().string());
        return out;
    }
    static std::string read(const fs::path& p) {
        std::ifstream in(p);
        std::stringstream s;
        s << in.rdbuf();
        return s.str();
    }
};

TEST_F(AtomicFile, WritesAndReplacesLeavingNoTemporaryFile) {
    const fs::path file = dir_ / "result.json";
    ASSERT_TRUE(core::writeFileAtomically(file, "first\n"));
    EXPECT_EQ(read(file), "first\n");
    ASSERT_TRUE(core::writeFileAtomically(file, "second\n"));
    EXPECT_EQ(read(file), "second\n");
    EXPECT_EQ(names(), std::vector<std::string>{"result.json"});
}

TEST_F(AtomicFile, NeverReplaceKeepsTheOldFileAndSaysEexist) {
    const fs::path file = dir_ / "s.ome.tif";
    ASSERT_TRUE(core::writeFileAtomically(file, "old", core::Replace::Never));
    auto r = core::writeFileAtomically(file, "new", core::Replace::Never);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, EEXIST);
    EXPECT_NE(r.error().message.find("s.ome.tif"), std::string::npos) << r.error().message;
    EXPECT_EQ(read(file), "old");
    EXPECT_EQ(names(), std::vector<std::string>{"s.ome.tif"});
}

TEST_F(AtomicFile, AFailedFillLeavesNothingAndAMissingDirectoryIsNotFound) {
    const fs::path file = dir_ / "labels.tif";
    fs::path seen;
    auto r = core::replaceAtomically(file, [&](int, const fs::path& tmp) -> core::Result<void> {
        seen = tmp;
        return core::makeError(ErrorCode::InvalidArgument, "no pixels");
    });
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().message, "no pixels");
    EXPECT_EQ(seen.parent_path(), dir_) << "the temporary file lies beside the target";
    EXPECT_TRUE(names().empty());

    auto missing = core::writeFileAtomically(dir_ / "no" / "such" / "x.json", "{}");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_EQ(missing.error().sysErrno, ENOENT);
}

TEST_F(AtomicFile, TheCleanUpKnowsTheWritersTemporaryNames) {
    fs::path seen;
    ASSERT_TRUE(core::replaceAtomically(
        dir_ / "slice-003.tif", [&](int fd, const fs::path& tmp) -> core::Result<void> {
            seen = tmp;
            return ::write(fd, "x", 1) == 1 ? core::Result<void>()
                                            : core::makeError(ErrorCode::IoError, "write");
        }));
    EXPECT_TRUE(core::isAtomicTemporaryName(seen.filename().string())) << seen;
    for (const char* yes :
         {".a.json.tmp.1.2.3", ".slice-003.tif.tmp.17.0.5", ".x.tmp.4242.3.81234"})
        EXPECT_TRUE(core::isAtomicTemporaryName(yes)) << yes;
    for (const char* no : {"a.json.tmp.1.2.3", ".a.tmp.1.2", ".a.tmp.1.2.x", ".tmp.1.2.3",
                           "result.json", ".a.partial", "a.json.tmp-42", ""})
        EXPECT_FALSE(core::isAtomicTemporaryName(no)) << no;
}

} // namespace
} // namespace slicestation::test
