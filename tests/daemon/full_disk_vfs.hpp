#pragma once
// A SQLite VFS for tests that wraps the real one (SQLite's own crash tests do the same): every
// call goes to the default VFS, except that while the disk is "full" every write fails with
// SQLITE_FULL, as writing to a full file system does. Installed as the default VFS, so the
// journal under test opens its file through it unchanged.
#include <sqlite3.h>

#include <atomic>
#include <cstring>
#include <stdexcept>

namespace slicestation::testing_vfs {

class FullDiskVfs {
public:
    /// Registers the VFS as the process's default (once); later journals open through it.
    static FullDiskVfs& install() {
        static FullDiskVfs vfs;
        return vfs;
    }
    void setFull(bool full) { full_().store(full); }
    /// Writes refused since install().
    int refusedWrites() const { return refused_().load(); }

private:
    FullDiskVfs() {
        real_() = sqlite3_vfs_find(nullptr);
        if (real_() == nullptr)
            throw std::runtime_error("no default SQLite VFS");
        static sqlite3_vfs shim{};
        shim.iVersion = 2;
        shim.szOsFile = static_cast<int>(sizeof(File)) + real_()->szOsFile;
        shim.mxPathname = real_()->mxPathname;
        shim.zName = "slst-full-disk";
        shim.xOpen = open;
        shim.xDelete = [](sqlite3_vfs*, const char* n, int s) {
            return real_()->xDelete(real_(), n, s);
        };
        shim.xAccess = [](sqlite3_vfs*, const char* n, int f, int* out) {
            return real_()->xAccess(real_(), n, f, out);
        };
        shim.xFullPathname = [](sqlite3_vfs*, const char* n, int size, char* out) {
            return real_()->xFullPathname(real_(), n, size, out);
        };
        shim.xDlOpen = [](sqlite3_vfs*, const char* n) { return real_()->xDlOpen(real_(), n); };
        shim.xDlError = [](sqlite3_vfs*, int n, char* out) { real_()->xDlError(real_(), n, out); };
        shim.xDlSym = [](sqlite3_vfs*, void* h, const char* s) {
            return real_()->xDlSym(real_(), h, s);
        };
        shim.xDlClose = [](sqlite3_vfs*, void* h) { real_()->xDlClose(real_(), h); };
        shim.xRandomness = [](sqlite3_vfs*, int n, char* out) {
            return real_()->xRandomness(real_(), n, out);
        };
        shim.xSleep = [](sqlite3_vfs*, int us) { return real_()->xSleep(real_(), us); };
        shim.xCurrentTime = [](sqlite3_vfs*, double* t) {
            return real_()->xCurrentTime(real_(), t);
        };
        shim.xGetLastError = [](sqlite3_vfs*, int n, char* out) {
            return real_()->xGetLastError(real_(), n, out);
        };
        shim.xCurrentTimeInt64 = [](sqlite3_vfs*, sqlite3_int64* t) {
            return real_()->xCurrentTimeInt64(real_(), t);
        };
        if (sqlite3_vfs_register(&shim, 1) != SQLITE_OK)
            throw std::runtime_error("cannot register the VFS");
    }

    struct File {
        sqlite3_file base;  // must come first: SQLite sees a sqlite3_file
        sqlite3_file* real; // the real VFS's file, right behind this struct
    };
    static sqlite3_file* inner(sqlite3_file* f) { return reinterpret_cast<File*>(f)->real; }

    static std::atomic<bool>& full_() {
        static std::atomic<bool> v{false};
        return v;
    }
    static std::atomic<int>& refused_() {
        static std::atomic<int> v{0};
        return v;
    }
    static sqlite3_vfs*& real_() {
        static sqlite3_vfs* v = nullptr;
        return v;
    }

    static const sqlite3_io_methods* methods() {
        static const sqlite3_io_methods m = [] {
            sqlite3_io_methods x{};
            x.iVersion = 3;
            x.xClose = [](sqlite3_file* f) { return inner(f)->pMethods->xClose(inner(f)); };
            x.xRead = [](sqlite3_file* f, void* b, int n, sqlite3_int64 o) {
                return inner(f)->pMethods->xRead(inner(f), b, n, o);
            };
            x.xWrite = [](sqlite3_file* f, const void* b, int n, sqlite3_int64 o) {
                if (full_().load()) {
                    ++refused_();
                    return SQLITE_FULL;
                }
                return inner(f)->pMethods->xWrite(inner(f), b, n, o);
            };
            x.xTruncate = [](sqlite3_file* f, sqlite3_int64 s) {
                return inner(f)->pMethods->xTruncate(inner(f), s);
            };
            x.xSync = [](sqlite3_file* f, int fl) {
                return inner(f)->pMethods->xSync(inner(f), fl);
            };
            x.xFileSize = [](sqlite3_file* f, sqlite3_int64* s) {
                return inner(f)->pMethods->xFileSize(inner(f), s);
            };
            x.xLock = [](sqlite3_file* f, int l) { return inner(f)->pMethods->xLock(inner(f), l); };
            x.xUnlock = [](sqlite3_file* f, int l) {
                return inner(f)->pMethods->xUnlock(inner(f), l);
            };
            x.xCheckReservedLock = [](sqlite3_file* f, int* out) {
                return inner(f)->pMethods->xCheckReservedLock(inner(f), out);
            };
            x.xFileControl = [](sqlite3_file* f, int op, void* arg) {
                return inner(f)->pMethods->xFileControl(inner(f), op, arg);
            };
            x.xSectorSize = [](sqlite3_file* f) {
                return inner(f)->pMethods->xSectorSize(inner(f));
            };
            x.xDeviceCharacteristics = [](sqlite3_file* f) {
                return inner(f)->pMethods->xDeviceCharacteristics(inner(f));
            };
            x.xShmMap = [](sqlite3_file* f, int page, int size, int extend, void volatile** out) {
                return inner(f)->pMethods->xShmMap(inner(f), page, size, extend, out);
            };
            x.xShmLock = [](sqlite3_file* f, int offset, int n, int flags) {
                return inner(f)->pMethods->xShmLock(inner(f), offset, n, flags);
            };
            x.xShmBarrier = [](sqlite3_file* f) { inner(f)->pMethods->xShmBarrier(inner(f)); };
            x.xShmUnmap = [](sqlite3_file* f, int del) {
                return inner(f)->pMethods->xShmUnmap(inner(f), del);
            };
            x.xFetch = [](sqlite3_file* f, sqlite3_int64 o, int n, void** out) {
                return inner(f)->pMethods->xFetch(inner(f), o, n, out);
            };
            x.xUnfetch = [](sqlite3_file* f, sqlite3_int64 o, void* p) {
                return inner(f)->pMethods->xUnfetch(inner(f), o, p);
            };
            return x;
        }();
        return &m;
    }

    static int open(sqlite3_vfs*, sqlite3_filename name, sqlite3_file* f, int flags,
                    int* outFlags) {
        auto* file = reinterpret_cast<File*>(f);
        file->real = reinterpret_cast<sqlite3_file*>(file + 1);
        std::memset(file->real, 0, static_cast<std::size_t>(real_()->szOsFile));
        const int rc = real_()->xOpen(real_(), name, file->real, flags, outFlags);
        // SQLite calls xClose only when pMethods is set; the real file's methods decide.
        file->base.pMethods = file->real->pMethods != nullptr ? methods() : nullptr;
        return rc;
    }
};

} // namespace slicestation::testing_vfs
