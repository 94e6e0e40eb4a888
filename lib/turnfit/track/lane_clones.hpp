// Versions of the group stepper's lane loops for wider vectors, chosen when the library loads.
#pragma once

/// TURNFIT_LANE_CLONES before a function's definition compiles it three times, for AVX-512,
/// AVX2 and the x86-64 baseline (SSE2), and the first that the processor has is called (GCC's
/// function multi-versioning through an ifunc resolver). The loops over a group's lanes then take
/// up to eight particles per instruction where the processor can, in the default portable build.
/// The numbers do not change: the files that use it are compiled without multiply-add
/// contraction (lib/CMakeLists.txt), and additions, products, divisions and square roots are
/// rounded alike at every vector width, so a lane's result is the same bit for bit on any
/// processor (the regeneration test of ring8's measurement and the README's main job check it
/// against files made with the baseline version). Off with -march=native (TURNFIT_NATIVE: the
/// compiler targets the processor anyway), with clang (its sanitizer and fuzzing builds) and
/// off x86-64.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(TURNFIT_NO_CLONES)
#define TURNFIT_LANE_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define TURNFIT_LANE_CLONES
#endif
