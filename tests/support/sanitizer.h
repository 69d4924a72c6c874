// Whether the test executable is built with a sanitizer: heavy validations (large meshes, long
// runs) and timing deadlines skip themselves there and run in the Release build (CI tiers,
// docs/building_and_testing.md).
#pragma once

namespace somasim::testing {

#if defined(__SANITIZE_ADDRESS__)
inline constexpr bool kUnderSanitizer = true;
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(undefined_behavior_sanitizer)
inline constexpr bool kUnderSanitizer = true;
#else
inline constexpr bool kUnderSanitizer = false;
#endif
#else
inline constexpr bool kUnderSanitizer = false;
#endif

}  // namespace somasim::testing
