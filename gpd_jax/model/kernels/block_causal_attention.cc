// Fused block-causal attention over a KV cache for XLA:CPU (an XLA FFI custom call).
//
// Why: in the KV-cached rollout, attention of one frame's queries against the filled cache is almost all of
// the work, and XLA:CPU cannot fuse a dot with a softmax: it writes every score block to memory, reads it
// back for the max, again for the exponentials, and runs those elementwise passes on one thread. This kernel
// transposes each 128-key block once into L1, keeps one query's 128 scores and its output accumulator in
// vector registers, uses an online softmax, and spreads (scenario, head) work items over XLA's intra-op
// thread pool.
//
// Semantics (identical to gpd_jax.attention.attend_dynamic): query i of a scenario sees key positions
// p < min((q_frame[i] + 1) * tokens_per_frame, num_chunks * chunk_len, S), i.e. its own and earlier frames,
// within the filled chunks. Queries are pre-scaled by 1/sqrt(Dh).
//
// Buffers (any number of leading batch dims, flattened to B):
//   q f32[B, H, Sq, Dh], k f32[B, H, S, Dh], v f32[B, H, S, Dh], q_frame s32[B, Sq], num_chunks s32[B]
//   -> out f32[B, H, Sq, Dh].
// Attributes: tokens_per_frame (i64), chunk_len (i64).
//
// Built on first use by gpd_jax/native.py with the system C++ compiler (-O3 -march=native); if that fails the
// pure-XLA path is used instead.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kKeyBlock = 128;  // keys per block: the transposed [Dh, 128] key tile stays in L1

// Sixteen floats (one AVX-512 register, two AVX2 or four SSE registers: GCC/Clang vector extensions, so the
// same source builds for any x86-64 or ARM target).
typedef float v16 __attribute__((vector_size(64)));
typedef int32_t i16v __attribute__((vector_size(64)));
typedef float v16u __attribute__((vector_size(64), aligned(4)));  // unaligned loads and stores
constexpr int kLanes = 16;
constexpr int kGroups = kKeyBlock / kLanes;

inline float hsum(v16 x) {
  float s = 0.0f;
  for (int i = 0; i < kLanes; ++i) s += x[i];
  return s;
}

inline float hmax(v16 x) {
  float m = x[0];
  for (int i = 1; i < kLanes; ++i) m = x[i] > m ? x[i] : m;
  return m;
}

// exp(x) for x <= 0 (scores minus their running max), lane-wise: 2^(x log2 e) with the fraction in
// [-0.5, 0.5] and a degree-7 Taylor polynomial (relative error < 1e-7); x < -87 (and -inf) gives exactly 0.
inline v16 exp_nonpositive(v16 x) {
  const v16 lo = x < -87.0f ? v16{} - 87.0f : x;  // also maps -inf
  const v16 t = lo * 1.4426950408889634f;
  const i16v n = __builtin_convertvector(t + (t < 0.0f ? v16{} - 0.5f : v16{} + 0.5f), i16v);  // round
  const v16 y = (t - __builtin_convertvector(n, v16)) * 0.6931471805599453f;
  v16 p = v16{} + 1.0f / 5040.0f;
  p = p * y + 1.0f / 720.0f;
  p = p * y + 1.0f / 120.0f;
  p = p * y + 1.0f / 24.0f;
  p = p * y + 1.0f / 6.0f;
  p = p * y + 0.5f;
  p = p * y + 1.0f;
  p = p * y + 1.0f;
  const i16v bits = (n + 127) << 23;
  v16 scale;
  __builtin_memcpy(&scale, &bits, sizeof(scale));
  return x < -87.0f ? v16{} : p * scale;
}

inline float exp_nonpositive(float x) { return exp_nonpositive(v16{} + x)[0]; }

struct Problem {
  const float* q;
  const float* k;
  const float* v;
  const int32_t* q_frame;
  const int32_t* num_chunks;
  float* out;
  int64_t heads, sq, s, dh, tokens_per_frame, chunk_len;
};

// Per-query limits: query i sees keys [0, limit[i]). Returns the largest.
int64_t Limits(const Problem& pb, int64_t b, std::vector<int64_t>& limit) {
  const int64_t filled = std::min<int64_t>(static_cast<int64_t>(pb.num_chunks[b]) * pb.chunk_len, pb.s);
  int64_t max_limit = 0;
  for (int64_t i = 0; i < pb.sq; ++i) {
    const int64_t f = pb.q_frame[b * pb.sq + i];
    limit[i] = std::max<int64_t>(0, std::min<int64_t>((f + 1) * pb.tokens_per_frame, filled));
    max_limit = std::max(max_limit, limit[i]);
  }
  return max_limit;
}

// One work item: every query of scenario b, head h (item = b * heads + h). Keys are visited in blocks of
// kKeyBlock, transposed once per block and shared by all queries; each query keeps an online softmax
// (running max m, sum l, unnormalized output acc). DH (a multiple of 16) is fixed at compile time so scores
// and accumulators live in vector registers.
template <int DH>
void RunItem(const Problem& pb, int64_t item) {
  constexpr int NV = DH / kLanes;
  const int64_t b = item / pb.heads;
  const float* __restrict q = pb.q + item * pb.sq * DH;
  const float* __restrict k = pb.k + item * pb.s * DH;
  const float* __restrict v = pb.v + item * pb.s * DH;
  float* __restrict out = pb.out + item * pb.sq * DH;

  std::vector<int64_t> limit(pb.sq);
  const int64_t max_limit = Limits(pb, b, limit);
  std::vector<v16> kt(static_cast<size_t>(DH) * kGroups);  // [DH][kGroups] transposed key block
  std::vector<v16> acc(static_cast<size_t>(pb.sq) * NV, v16{});
  std::vector<float> m(pb.sq, -INFINITY), l(pb.sq, 0.0f);
  alignas(64) float p[kKeyBlock];
  v16 lane;
  for (int i = 0; i < kLanes; ++i) lane[i] = static_cast<float>(i);

  for (int64_t start = 0; start < max_limit; start += kKeyBlock) {
    const int64_t nk = std::min<int64_t>(kKeyBlock, max_limit - start);
    float* ktf = reinterpret_cast<float*>(kt.data());
    for (int64_t j = 0; j < kKeyBlock; ++j)
      for (int d = 0; d < DH; ++d) ktf[d * kKeyBlock + j] = j < nk ? k[(start + j) * DH + d] : 0.0f;
    const float* __restrict vb = v + start * DH;

    for (int64_t i = 0; i < pb.sq; ++i) {
      const int64_t n = std::min<int64_t>(nk, limit[i] - start);
      if (n <= 0) continue;
      const int groups = static_cast<int>((n + kLanes - 1) / kLanes);
      const float* __restrict qi = q + i * DH;
      v16 sc[kGroups];
      for (int g = 0; g < kGroups; ++g) sc[g] = v16{};
      for (int d = 0; d < DH; ++d) {
        const float qd = qi[d];
        const v16* row = kt.data() + d * kGroups;
        for (int g = 0; g < groups; ++g) sc[g] += qd * row[g];
      }
      v16 vmax = v16{} - INFINITY;
      for (int g = 0; g < groups; ++g) {
        sc[g] = lane + static_cast<float>(g * kLanes) < static_cast<float>(n) ? sc[g] : v16{} - INFINITY;
        vmax = sc[g] > vmax ? sc[g] : vmax;
      }
      const float m_new = std::max(m[i], hmax(vmax));
      const float corr = exp_nonpositive(m[i] - m_new);  // m = -inf on the first block: 0
      v16 vsum = v16{};
      for (int g = 0; g < groups; ++g) {
        const v16 e = exp_nonpositive(sc[g] - m_new);
        vsum += e;
        *reinterpret_cast<v16*>(p + g * kLanes) = e;
      }
      l[i] = l[i] * corr + hsum(vsum);
      m[i] = m_new;
      // acc += p @ V over the block, four independent accumulators per output vector to hide FMA latency.
      for (int c = 0; c < NV; ++c) {
        v16 a0 = acc[i * NV + c] * corr, a1 = v16{}, a2 = v16{}, a3 = v16{};
        const float* vc = vb + c * kLanes;
        int64_t j = 0;
        for (; j + 4 <= n; j += 4) {
          a0 += p[j] * *reinterpret_cast<const v16u*>(vc + j * DH);
          a1 += p[j + 1] * *reinterpret_cast<const v16u*>(vc + (j + 1) * DH);
          a2 += p[j + 2] * *reinterpret_cast<const v16u*>(vc + (j + 2) * DH);
          a3 += p[j + 3] * *reinterpret_cast<const v16u*>(vc + (j + 3) * DH);
        }
        for (; j < n; ++j) a0 += p[j] * *reinterpret_cast<const v16u*>(vc + j * DH);
        acc[i * NV + c] = (a0 + a1) + (a2 + a3);
      }
    }
  }
  for (int64_t i = 0; i < pb.sq; ++i) {
    const float inv = l[i] > 0.0f ? 1.0f / l[i] : 0.0f;  // a query that sees no key gets zeros
    for (int c = 0; c < NV; ++c) *reinterpret_cast<v16u*>(out + (i * NV + c) * kLanes) = acc[i * NV + c] * inv;
  }
}

// Any head size: the same algorithm in plain loops.
void RunItemGeneric(const Problem& pb, int64_t item) {
  const int64_t dh = pb.dh, b = item / pb.heads;
  const float* q = pb.q + item * pb.sq * dh;
  const float* k = pb.k + item * pb.s * dh;
  const float* v = pb.v + item * pb.s * dh;
  float* out = pb.out + item * pb.sq * dh;
  std::vector<int64_t> limit(pb.sq);
  Limits(pb, b, limit);
  std::vector<float> sc;
  for (int64_t i = 0; i < pb.sq; ++i) {
    const int64_t n = limit[i];
    sc.assign(n, 0.0f);
    float mx = -INFINITY;
    for (int64_t j = 0; j < n; ++j) {
      for (int64_t d = 0; d < dh; ++d) sc[j] += q[i * dh + d] * k[j * dh + d];
      mx = std::max(mx, sc[j]);
    }
    float sum = 0.0f;
    for (int64_t j = 0; j < n; ++j) sum += (sc[j] = std::exp(sc[j] - mx));
    const float inv = sum > 0.0f ? 1.0f / sum : 0.0f;
    for (int64_t d = 0; d < dh; ++d) {
      float o = 0.0f;
      for (int64_t j = 0; j < n; ++j) o += sc[j] * v[j * dh + d];
      out[i * dh + d] = o * inv;
    }
  }
}

void RunItemDispatch(const Problem& pb, int64_t item) {
  switch (pb.dh) {
    case 16: return RunItem<16>(pb, item);
    case 32: return RunItem<32>(pb, item);
    case 48: return RunItem<48>(pb, item);
    case 64: return RunItem<64>(pb, item);
    case 128: return RunItem<128>(pb, item);
    default: return RunItemGeneric(pb, item);
  }
}

// Work shared by the calling thread and pool tasks through an atomic counter. The caller waits only for
// items that were claimed, never for a task to start, so a busy (or size-1) pool cannot deadlock it; tasks
// that start late find nothing left and return. The state is shared so such late tasks never dangle.
struct Shared {
  Problem pb;
  int64_t total;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> done{0};
  std::mutex mu;
  std::condition_variable cv;

  void Work() {
    int64_t finished = 0;
    for (int64_t i = next.fetch_add(1); i < total; i = next.fetch_add(1)) {
      RunItemDispatch(pb, i);
      ++finished;
    }
    if (finished && done.fetch_add(finished) + finished == total) {
      std::lock_guard<std::mutex> lock(mu);
      cv.notify_all();
    }
  }
};

ffi::Error Attention(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> q, ffi::Buffer<ffi::F32> k,
                     ffi::Buffer<ffi::F32> v, ffi::Buffer<ffi::S32> q_frame, ffi::Buffer<ffi::S32> num_chunks,
                     ffi::ResultBuffer<ffi::F32> out, int64_t tokens_per_frame, int64_t chunk_len) {
  const auto qd = q.dimensions();
  const auto kd = k.dimensions();
  if (qd.size() < 3 || kd.size() != qd.size() || v.dimensions().size() != qd.size())
    return ffi::Error::InvalidArgument("block_causal_attention: q, k, v must be [..., H, S, Dh] of equal rank");
  const size_t r = qd.size();
  const int64_t heads = qd[r - 3], sq = qd[r - 2], dh = qd[r - 1], s = kd[r - 2];
  int64_t batch = 1;
  for (size_t i = 0; i + 3 < r; ++i) {
    if (kd[i] != qd[i]) return ffi::Error::InvalidArgument("block_causal_attention: q and k batch dims differ");
    batch *= qd[i];
  }
  if (kd[r - 3] != heads || kd[r - 1] != dh)
    return ffi::Error::InvalidArgument("block_causal_attention: k must have q's heads and head size");
  if (static_cast<int64_t>(q_frame.element_count()) != batch * sq ||
      static_cast<int64_t>(num_chunks.element_count()) != batch)
    return ffi::Error::InvalidArgument("block_causal_attention: q_frame must be [..., Sq], num_chunks [...]");
  if (tokens_per_frame <= 0 || chunk_len <= 0)
    return ffi::Error::InvalidArgument("block_causal_attention: tokens_per_frame and chunk_len must be > 0");

  auto shared = std::make_shared<Shared>();
  shared->pb = Problem{q.typed_data(), k.typed_data(), v.typed_data(), q_frame.typed_data(),
                       num_chunks.typed_data(), out->typed_data(), heads, sq, s, dh, tokens_per_frame,
                       chunk_len};
  shared->total = batch * heads;
  if (shared->total == 0) return ffi::Error::Success();

  const int64_t helpers = std::min<int64_t>(pool.num_threads(), shared->total) - 1;
  for (int64_t t = 0; t < helpers; ++t) pool.Schedule([shared] { shared->Work(); });
  shared->Work();
  std::unique_lock<std::mutex> lock(shared->mu);
  shared->cv.wait(lock, [&] { return shared->done.load() == shared->total; });
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(GpdBlockCausalAttention, Attention,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Attr<int64_t>("tokens_per_frame")
                                  .Attr<int64_t>("chunk_len"));
