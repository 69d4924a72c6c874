// The files and folders the tests write under the system temp dir. Each is registered with the
// process that made it; when that process's tests end (each ctest test runs in a process of its
// own) they are removed if every test passed, and kept, with "kept test files: <paths>" on
// stderr, if one failed, for debugging. SOMASIM_KEEP_TEST_FILES=1 keeps them in any case.
// A test process that crashes or is killed keeps its files too (nothing runs to remove them).
#pragma once

#include <string>

namespace somasim::testing {

// A fresh empty directory <temp>/<prefix>-XXXXXX for files a test writes, registered (below).
// Fails the test and returns "" when it cannot be made.
std::string MakeTempDir(const std::string& prefix);

// This process's directory for `prefix`: made (as MakeTempDir(<prefix>-<pid>)) on the first call
// in a process, the same one on later calls, for helpers that share a folder between tests.
std::string ProcessTempDir(const std::string& prefix);

// Removes `path` (a file or a folder with everything in it) at the end of this process's tests
// when they all passed. Only the registering process removes it: a forked child that ends never
// deletes its parent's files.
void RegisterTempPath(const std::string& path);

}  // namespace somasim::testing
