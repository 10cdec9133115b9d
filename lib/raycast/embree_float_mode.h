#pragma once

// The floating-point mode Embree expects on a thread that traces rays:
// flush-to-zero and denormals-are-zero set in MXCSR (Embree's performance
// recommendations). Without them a ray whose numbers go denormal (a far
// origin over a tiny scene, a nearly parallel direction) takes the CPU's
// slow denormal path at every box and triangle test. The mode is restored
// when the guard ends, because the same pool threads run the exact method,
// whose error filters count on gradual underflow.

#if defined(__SSE__) || defined(__x86_64__)
#include <pmmintrin.h>  // _MM_DENORMALS_ZERO_ON
#include <xmmintrin.h>  // _MM_FLUSH_ZERO_ON
#endif

namespace visq::raycast {

class EmbreeFloatMode {
 public:
  EmbreeFloatMode() {
#if defined(__SSE__) || defined(__x86_64__)
    saved_ = _mm_getcsr();
    _mm_setcsr(saved_ | _MM_FLUSH_ZERO_ON | _MM_DENORMALS_ZERO_ON);
#endif
  }
  ~EmbreeFloatMode() {
#if defined(__SSE__) || defined(__x86_64__)
    _mm_setcsr(saved_);
#endif
  }
  EmbreeFloatMode(const EmbreeFloatMode&) = delete;
  EmbreeFloatMode& operator=(const EmbreeFloatMode&) = delete;

 private:
#if defined(__SSE__) || defined(__x86_64__)
  unsigned saved_ = 0;
#endif
};

}  // namespace visq::raycast
