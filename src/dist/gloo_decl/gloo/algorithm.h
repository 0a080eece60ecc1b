// Declarations only: see ../README.md.
#pragma once
#include "context.h"
