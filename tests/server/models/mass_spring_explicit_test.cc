// Tests of the explicit mass-spring step's kernels (issue 4 speed work).
#include <gtest/gtest.h>

#include "server/models/mass_spring_model.h"
