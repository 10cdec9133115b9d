// The partial sums of a sharded bake and their merge are part of the public
// API (installed clients merge shards with them): the definition is in the
// public floor, include/visq/obscurance_partial.h.
#pragma once

#include "visq/obscurance_partial.h"
