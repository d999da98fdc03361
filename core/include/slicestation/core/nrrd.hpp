#pragma once
/// Reading 3-D NRRD volumes (Allen CCF annotation and template files).
/// Format: http://teem.sourceforge.net/nrrd/format.html

#include "slicestation/core/result.hpp"

#include <array>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

namespace slicestation::core {

/// A 3-D volume of non-negative integer voxels, widened to uint32.
struct Volume {
    std::array<int, 3> sizes{};        ///< voxels per axis, fastest axis first (NRRD order)
    std::array<double, 3> spacingUm{}; ///< from "space directions" (vector length) or "spacings";
                                       ///< 0 when absent
    std::vector<std::uint32_t> data;   ///< sizes[0]*sizes[1]*sizes[2] values,
                                       ///< index = i0 + s0*(i1 + s1*i2)
    std::string type;                  ///< NRRD type as read, e.g. "unsigned int", "unsigned short"

    /// Voxel at (i0, i1, i2); indices must lie inside `sizes` (asserted).
    std::uint32_t at(int i0, int i1, int i2) const;
};

/// Largest volume readNrrd accepts, as held in memory (uint32 per voxel): 2 GiB, i.e.
/// 536870912 voxels. The Allen 25 um annotation (528 x 320 x 456) takes 308 MB; the 10 um one
/// (1320 x 800 x 1140, 4.8 GB) is refused: slice the 25 um volume instead.
inline constexpr std::uint64_t kMaxVolumeBytes = std::uint64_t{2} << 30;

/// Reads a 3-D NRRD file with attached header ("NRRD0001".."NRRD0005").
///
/// Types: uint8/16/32 and int8/16/32 under any of NRRD's spellings; a negative voxel is an error
/// (Unsupported); float, double and 64-bit types are Unsupported. Encodings: raw and gzip
/// (also zlib-wrapped); endian little or big. Space units are taken to be micrometres.
/// Not supported: detached data ("data file:"), "line skip"/"byte skip", other encodings.
/// Limits, checked from the header before any data is decoded: sizes product at most
/// kMaxVolumeBytes / 4 voxels, file at most kMaxVolumeBytes + 1 MiB, gzip data no shorter than
/// deflate's best ratio (1032:1) allows for the claimed size; voxel sizes 0 (unknown) or within
/// [0.001, 1e6] um.
/// Blocking file I/O; re-entrant.
///
/// \return the volume; NotFound (no such file), IoError (unreadable, empty, header without the
///         blank line that ends it, truncated or corrupt data, bad gzip stream, gzip data too
///         short for the claimed size), InvalidArgument (not a NRRD file, missing or malformed
///         field, voxel size out of range: the message names file and field), Unsupported
///         (valid NRRD this reader does not handle: dimension other than 3, type, encoding,
///         detached data, negative voxels, a volume or file beyond the limits).
[[nodiscard]] Result<Volume> readNrrd(const std::filesystem::path& path);

} // namespace slicestation::core
