// availableBytes: agrees with statvfs, follows what is written, and reports its errors.
#include "../../common/test_dir.hpp"
#include "slicestation/daemon/storage/disk_space.hpp"

#include <gtest/gtest.h>

#include <stdlib.h>
#include <sys/mount.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <cerrno>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

namespace slicestation::test {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;

TEST(DiskSpace, AgreesWithStatvfs) {
    testing_dir::ScratchDir dir("disk");
    auto bytes = daemon::availableBytes(dir.path());
    ASSERT_TRUE(bytes) << bytes.error().message;
    struct statvfs st {};
    ASSERT_EQ(::statvfs(dir.path().c_str(), &st), 0);
    const double expected = static_cast<double>(st.f_bavail) * static_cast<double>(st.f_frsize);
    // Other processes write meanwhile: agree within 64 MiB.
    EXPECT_NEAR(static_cast<double>(*bytes), expected, 64.0 * 1024 * 1024);
}

TEST(DiskSpace, FollowsWritesOnASmallFileSystem) {
    if (::geteuid() != 0)
        GTEST_SKIP() << "needs root to mount a tmpfs";
    testing_dir::ScratchDir dir("disk");
    const fs::path mnt = dir.path() / "m";
    fs::create_directories(mnt);
    if (::mount("tmpfs", mnt.c_str(), "tmpfs", 0, "size=1m") != 0) {
        GTEST_SKIP() << "not permitted to mount a tmpfs";
    }
    struct Unmount {
        const fs::path& at;
        ~Unmount() { ::umount2(at.c_str(), MNT_DETACH); }
    } unmount{mnt};
    auto before = daemon::availableBytes(mnt);
    ASSERT_TRUE(before);
    EXPECT_LE(*before, 1024u * 1024u);
    EXPECT_GT(*before, 900u * 1024u);
    {
        std::ofstream out(mnt / "f", std::ios::binary);
        const std::vector<char> chunk(256 * 1024, 'x');
        out.write(chunk.data(), static_cast<std::streamsize>(chunk.size()));
    }
    auto after = daemon::availableBytes(mnt);
    ASSERT_TRUE(after);
    EXPECT_EQ(*before - *after, 256u * 1024u);
}

TEST(DiskSpace, MissingDirectoryIsNotFound) {
    testing_dir::ScratchDir dir("disk");
    auto r = daemon::availableBytes(dir.path() / "gone");
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::NotFound);
    EXPECT_EQ(r.error().sysErrno, ENOENT);
    EXPECT_NE(r.error().message.find("gone"), std::string::npos);
}

TEST(DiskSpace, OtherFailuresAreIoErrorsWithErrno) {
    testing_dir::ScratchDir dir("disk");
    const fs::path loop = dir.path() / "loop";
    fs::create_symlink(loop, loop); // resolving it fails with ELOOP
    auto r = daemon::availableBytes(loop);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, ELOOP);
}

} // namespace
} // namespace slicestation::test
