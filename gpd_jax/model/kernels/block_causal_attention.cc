// Fused block-causal attention over a KV cache for XLA:CPU (an XLA FFI custom call).
//
// Why: in the KV-cached rollout, attention of one frame's queries against the filled cache is almost all of
// the work, and XLA:CPU cannot fuse a dot with a softmax: it writes every score block to memory, reads it
// back for the max, again for the exponentials, and runs those elementwise passes on one thread. This kernel
// transposes each block of kKeyBlock keys once into L1, computes a [kQueryTile x block] score tile in vector
// registers, runs an online softmax on it in L1 and accumulates the output tile in registers; (scenario, head,
// query range) work items are spread over XLA's intra-op thread pool.
//
// Vectors are the target's native width (W floats: 16 with AVX-512, 8 with AVX2, 4 with SSE or NEON), chosen
// at compile time. An earlier version used 16-float vectors everywhere: on AVX2 GCC splits such vectors for
// arithmetic but lowers their compares and selects lane by lane into scalar code, which made the kernel ten
// times slower than XLA there. Register tiles are sized so the accumulators fit in 16 vector registers.
//
// Semantics (identical to gpd_jax.model.attention.attend_dynamic): query i of a scenario sees key positions
// p < min((q_frame[i] + 1) * tokens_per_frame, num_chunks * chunk_len, S), i.e. its own and earlier frames,
// within the filled chunks. Queries are pre-scaled by 1/sqrt(Dh).
//
// Buffers (any number of leading batch dims, flattened to B):
//   q f32[B, H, Sq, Dh], k f32[B, H, S, Dh], v f32[B, H, S, Dh], q_frame s32[B, Sq], num_chunks s32[B]
//   -> out f32[B, H, Sq, Dh]. GpdBlockCausalAttentionBf16 takes a bfloat16 cache (k, v bf16[B, H, S, Dh]: half
//   the bytes read) and widens each key block and value block to float32 in L1; the arithmetic is float32.
// Attributes: tokens_per_frame (i64), chunk_len (i64).
//
// Built on first use by gpd_jax/model/native.py with the system C++ compiler (-O3 -march=$GPD_JAX_NATIVE_MARCH,
// default native); if that fails the pure-XLA path is used instead. GpdAttentionVectorWidth() reports W.

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

#if defined(__AVX512F__)
constexpr int W = 16;
#elif defined(__AVX2__)
constexpr int W = 8;
#else
constexpr int W = 4;  // SSE2 (every x86-64) or NEON: 128-bit vectors
#endif

typedef float vf __attribute__((vector_size(W * 4)));
typedef int32_t vi __attribute__((vector_size(W * 4)));
typedef float vfu __attribute__((vector_size(W * 4), aligned(4)));  // unaligned loads and stores

constexpr int kKeyBlock = 64;   // keys per block: the transposed [Dh, 64] key tile stays in L1
#ifndef GPD_QUERY_TILE
#define GPD_QUERY_TILE 4
#endif
constexpr int kQueryTile = GPD_QUERY_TILE;  // queries per register tile
constexpr int kKeyVecs = kKeyBlock / W;
constexpr int kSub = 2;         // key vectors per score sub-tile: kQueryTile * kSub accumulators

// Keeps a loaded vector in a register: without it the compiler folds the load into every FMA that uses it,
// which doubles the loads of the inner loops and makes them load-bound.
#if defined(__x86_64__) || defined(__i386__)
#define GPD_IN_REG(x) __asm__("" : "+x"(x))
#elif defined(__aarch64__)
#define GPD_IN_REG(x) __asm__("" : "+w"(x))
#else
#define GPD_IN_REG(x) (void)0
#endif

inline float hsum(vf x) {
  float s = 0.0f;
  for (int i = 0; i < W; ++i) s += x[i];
  return s;
}

inline float hmax(vf x) {
  float m = x[0];
  for (int i = 1; i < W; ++i) m = std::max(m, x[i]);
  return m;
}

inline vf splat(float x) { return vf{} + x; }

// 2^t for t <= 0, lane-wise: 2^round(t) (exponent bits) times a degree-5 polynomial for 2^f, f in [-0.5, 0.5]
// (coefficients fitted for relative error; measured max relative error 2.4e-7). t is clamped at -126, so
// -inf and anything below gives about 1e-38, never a denormal or garbage; callers zero masked lanes.
inline vf exp2_nonpositive(vf t) {
  t = t > -126.0f ? t : splat(-126.0f);
  const vi n = __builtin_convertvector(t - 0.5f, vi);  // round to nearest: t <= 0 and conversion truncates
  const vf f = t - __builtin_convertvector(n, vf);
  vf p = splat(1.327647129073739e-3f);
  p = p * f + 9.675540961325169e-3f;
  p = p * f + 5.550713092088699e-2f;
  p = p * f + 2.4022120237350464e-1f;
  p = p * f + 6.931469440460205e-1f;
  p = p * f + 1.0000001192092896f;
  const vi bits = (n + 127) << 23;
  vf scale;
  __builtin_memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}

inline float exp2_nonpositive(float t) { return exp2_nonpositive(splat(t))[0]; }

// bfloat16 is the top half of a float32: widening is a shift
inline float Bf16ToF32(uint16_t h) {
  const uint32_t u = static_cast<uint32_t>(h) << 16;
  float f;
  __builtin_memcpy(&f, &u, sizeof(f));
  return f;
}

// Key or value j, component d, of one (scenario, head) item whose rows start at row0 (either dtype)
inline float KvAt(const float* f32, const uint16_t* b16, int64_t row0, int64_t dh, int64_t j, int64_t d) {
  return b16 ? Bf16ToF32(b16[(row0 + j) * dh + d]) : f32[(row0 + j) * dh + d];
}

struct Problem {
  const float* q;
  const float* k;  // float32 keys and values, or (k16, v16 set, these null) bfloat16 ones
  const float* v;
  const uint16_t* k16;
  const uint16_t* v16;
  const int32_t* q_frame;
  const int32_t* num_chunks;
  float* out;
  int64_t heads, sq, s, dh, tokens_per_frame, chunk_len;
  int64_t query_parts;  // each (scenario, head) item's queries are split into this many work units
};

// Per-query limits: query i sees keys [0, limit[i]). Returns the largest over [i0, i1).
int64_t Limits(const Problem& pb, int64_t b, int64_t i0, int64_t i1, std::vector<int64_t>& limit) {
  const int64_t filled = std::min<int64_t>(static_cast<int64_t>(pb.num_chunks[b]) * pb.chunk_len, pb.s);
  int64_t max_limit = 0;
  for (int64_t i = i0; i < i1; ++i) {
    const int64_t f = pb.q_frame[b * pb.sq + i];
    limit[i] = std::max<int64_t>(0, std::min<int64_t>((f + 1) * pb.tokens_per_frame, filled));
    max_limit = std::max(max_limit, limit[i]);
  }
  return max_limit;
}

// Queries [i0, i1) of one (scenario, head) item. Keys are visited in blocks of kKeyBlock, transposed once
// per block and shared by all these queries; each query keeps an online softmax (running max m, sum l,
// unnormalized output acc). DH (a multiple of 16, so of W) is fixed at compile time so tiles live in
// registers.
template <int DH>
void RunItem(const Problem& pb, int64_t item, int64_t i0, int64_t i1) {
  constexpr int NV = DH / W;                   // vectors per head row
  constexpr int CV = NV >= 2 ? 2 : 1;          // output vectors per query in one PV pass
  constexpr int JU = kQueryTile * CV >= 8 ? 1 : 2;  // independent accumulator sets to hide FMA latency
  constexpr float kLog2e = 1.4426950408889634f;
  const int64_t b = item / pb.heads;
  const float* __restrict q = pb.q + item * pb.sq * DH;
  const int64_t row0 = item * pb.s;  // this item's first key / value row
  float* __restrict out = pb.out + item * pb.sq * DH;
  // bfloat16 values are widened a block at a time into this L1 buffer; float32 ones are read in place
  std::vector<float> vwide(pb.v16 ? static_cast<size_t>(kKeyBlock) * DH : 0);

  std::vector<int64_t> limit(pb.sq);
  const int64_t max_limit = Limits(pb, b, i0, i1, limit);
  const int64_t nq = i1 - i0;
  const int64_t ntiles = (nq + kQueryTile - 1) / kQueryTile;
  std::vector<vf> kt(static_cast<size_t>(DH) * kKeyVecs);   // [DH][kKeyBlock] transposed key block
  std::vector<vf> acc(static_cast<size_t>(ntiles) * kQueryTile * NV, vf{});
  // queries times log2(e), tile-padded with zeros: scores come out in base 2, so the softmax needs 2^x only
  std::vector<float> qs(static_cast<size_t>(ntiles) * kQueryTile * DH, 0.0f);
  for (int64_t i = 0; i < nq * DH; ++i) qs[i] = q[i0 * DH + i] * kLog2e;
  std::vector<float> m(ntiles * kQueryTile, -INFINITY), l(ntiles * kQueryTile, 0.0f);
  std::vector<int64_t> lim(ntiles * kQueryTile, 0);
  for (int64_t i = 0; i < nq; ++i) lim[i] = limit[i0 + i];
  alignas(64) float p[kQueryTile][kKeyBlock];
  vf lane;
  for (int i = 0; i < W; ++i) lane[i] = static_cast<float>(i);

  for (int64_t start = 0; start < max_limit; start += kKeyBlock) {
    const int64_t nk = std::min<int64_t>(kKeyBlock, max_limit - start);
    float* ktf = reinterpret_cast<float*>(kt.data());
    if (pb.k16) {
      const uint16_t* kb = pb.k16 + (row0 + start) * DH;
      for (int64_t j = 0; j < nk; ++j)
        for (int d = 0; d < DH; ++d) ktf[d * kKeyBlock + j] = Bf16ToF32(kb[j * DH + d]);
    } else {
      const float* kb = pb.k + (row0 + start) * DH;
      for (int64_t j = 0; j < nk; ++j)
        for (int d = 0; d < DH; ++d) ktf[d * kKeyBlock + j] = kb[j * DH + d];
    }
    for (int64_t j = nk; j < kKeyBlock; ++j)
      for (int d = 0; d < DH; ++d) ktf[d * kKeyBlock + j] = 0.0f;
    if (pb.v16) {
      const uint16_t* v16 = pb.v16 + (row0 + start) * DH;
      for (int64_t i = 0; i < nk * DH; ++i) vwide[i] = Bf16ToF32(v16[i]);
    }
    const float* __restrict vb = pb.v16 ? vwide.data() : pb.v + (row0 + start) * DH;

    for (int64_t tile = 0; tile < ntiles; ++tile) {
      const int64_t base = tile * kQueryTile;
      int64_t n[kQueryTile], nmax = 0;
      for (int t = 0; t < kQueryTile; ++t) {
        n[t] = std::min<int64_t>(nk, lim[base + t] - start);
        nmax = std::max(nmax, n[t]);
      }
      if (nmax <= 0) continue;
      const float* __restrict qt = qs.data() + base * DH;

      // scores: sub-tiles of kQueryTile queries x (kSub * W) keys held in registers; keys a query cannot see
      // get -inf; each query's block max is kept in a register
      const int nsub = static_cast<int>((nmax + kSub * W - 1) / (kSub * W));
      vf vmax[kQueryTile];
      for (int t = 0; t < kQueryTile; ++t) vmax[t] = splat(-INFINITY);
      for (int st = 0; st < nsub; ++st) {
        const float* qp = qt;
        __asm__("" : "+r"(qp));  // reload the query scalars in every sub-tile rather than keep 64 broadcasts
        vf a[kQueryTile][kSub];
        for (int t = 0; t < kQueryTile; ++t)
          for (int u = 0; u < kSub; ++u) a[t][u] = vf{};
#pragma GCC unroll 16
        for (int d = 0; d < DH; ++d) {
          const vf* row = kt.data() + d * kKeyVecs + st * kSub;
          vf kv[kSub];
          for (int u = 0; u < kSub; ++u) {
            kv[u] = row[u];
            GPD_IN_REG(kv[u]);
          }
          for (int t = 0; t < kQueryTile; ++t) {
            const vf qd = splat(qp[t * DH + d]);
            for (int u = 0; u < kSub; ++u) a[t][u] += qd * kv[u];
          }
        }
        const int64_t end = (st + 1) * kSub * W;
        for (int t = 0; t < kQueryTile; ++t) {
          if (n[t] < end) {  // partly visible sub-tile (the block's end, a frame boundary, tile padding)
            for (int u = 0; u < kSub; ++u) {
              const float first = static_cast<float>((st * kSub + u) * W);
              a[t][u] = lane + first < static_cast<float>(n[t]) ? a[t][u] : splat(-INFINITY);
            }
          }
          for (int u = 0; u < kSub; ++u) {
            vmax[t] = a[t][u] > vmax[t] ? a[t][u] : vmax[t];
            *reinterpret_cast<vf*>(&p[t][(st * kSub + u) * W]) = a[t][u];
          }
        }
      }

      // online softmax per query (base 2); p becomes 2^(score - max), exactly 0 for keys the query cannot see
      const int groups = nsub * kSub;
      float corr[kQueryTile];
      for (int t = 0; t < kQueryTile; ++t) {
        vf* pt = reinterpret_cast<vf*>(p[t]);
        if (n[t] <= 0) {  // this query sees no key of the block (or is tile padding)
          for (int g = 0; g < groups; ++g) pt[g] = vf{};
          corr[t] = 1.0f;
          continue;
        }
        const int full = static_cast<int>(n[t] / W);  // groups the query sees entirely
        const float m_old = m[base + t];
        const float m_new = std::max(m_old, hmax(vmax[t]));
        corr[t] = exp2_nonpositive(m_old - m_new);  // m = -inf on the first block: about 1e-38 times acc = 0
        const vf mv = splat(m_new);
        vf s0 = vf{}, s1 = vf{};
        int g = 0;
        for (; g + 2 <= full; g += 2) {
          const vf e0 = exp2_nonpositive(pt[g] - mv), e1 = exp2_nonpositive(pt[g + 1] - mv);
          pt[g] = e0;
          pt[g + 1] = e1;
          s0 += e0;
          s1 += e1;
        }
        for (; g < groups; ++g) {
          vf e = exp2_nonpositive(pt[g] - mv);
          if (g >= full) e = lane + static_cast<float>(g * W) < static_cast<float>(n[t]) ? e : vf{};
          pt[g] = e;
          s0 += e;
        }
        l[base + t] = l[base + t] * corr[t] + hsum(s0 + s1);
        m[base + t] = m_new;
      }

      // acc = acc * corr + p @ V over the block, CV output vectors per query at a time, in registers
      for (int c0 = 0; c0 < NV; c0 += CV) {
        vf o[JU][kQueryTile][CV];
        for (int t = 0; t < kQueryTile; ++t)
          for (int c = 0; c < CV; ++c) {
            o[0][t][c] = acc[(base + t) * NV + c0 + c] * corr[t];
            for (int u = 1; u < JU; ++u) o[u][t][c] = vf{};
          }
        const float* __restrict vc = vb + c0 * W;
        int64_t j = 0;
        for (; j + JU <= nmax; j += JU) {
          for (int u = 0; u < JU; ++u) {
            vf vr[CV];
            for (int c = 0; c < CV; ++c) {
              vr[c] = *reinterpret_cast<const vfu*>(vc + (j + u) * DH + c * W);
              GPD_IN_REG(vr[c]);
            }
            for (int t = 0; t < kQueryTile; ++t) {
              const vf pj = splat(p[t][j + u]);
              for (int c = 0; c < CV; ++c) o[u][t][c] += pj * vr[c];
            }
          }
        }
        for (; j < nmax; ++j) {
          vf vr[CV];
          for (int c = 0; c < CV; ++c) vr[c] = *reinterpret_cast<const vfu*>(vc + j * DH + c * W);
          for (int t = 0; t < kQueryTile; ++t)
            for (int c = 0; c < CV; ++c) o[0][t][c] += p[t][j] * vr[c];
        }
        for (int t = 0; t < kQueryTile; ++t)
          for (int c = 0; c < CV; ++c) {
            vf sum = o[0][t][c];
            for (int u = 1; u < JU; ++u) sum += o[u][t][c];
            acc[(base + t) * NV + c0 + c] = sum;
          }
      }
    }
  }
  for (int64_t i = 0; i < nq; ++i) {
    const float inv = l[i] > 0.0f ? 1.0f / l[i] : 0.0f;  // a query that sees no key gets zeros
    for (int c = 0; c < NV; ++c)
      *reinterpret_cast<vfu*>(out + (i0 + i) * DH + c * W) = acc[i * NV + c] * inv;
  }
}

// Any head size: the same algorithm in plain loops.
void RunItemGeneric(const Problem& pb, int64_t item, int64_t i0, int64_t i1) {
  const int64_t dh = pb.dh, b = item / pb.heads, row0 = item * pb.s;
  const float* q = pb.q + item * pb.sq * dh;
  float* out = pb.out + item * pb.sq * dh;
  std::vector<int64_t> limit(pb.sq);
  Limits(pb, b, i0, i1, limit);
  std::vector<float> sc;
  for (int64_t i = i0; i < i1; ++i) {
    const int64_t n = limit[i];
    sc.assign(n, 0.0f);
    float mx = -INFINITY;
    for (int64_t j = 0; j < n; ++j) {
      for (int64_t d = 0; d < dh; ++d) sc[j] += q[i * dh + d] * KvAt(pb.k, pb.k16, row0, dh, j, d);
      mx = std::max(mx, sc[j]);
    }
    float sum = 0.0f;
    for (int64_t j = 0; j < n; ++j) sum += (sc[j] = std::exp(sc[j] - mx));
    const float inv = sum > 0.0f ? 1.0f / sum : 0.0f;
    for (int64_t d = 0; d < dh; ++d) {
      float o = 0.0f;
      for (int64_t j = 0; j < n; ++j) o += sc[j] * KvAt(pb.v, pb.v16, row0, dh, j, d);
      out[i * dh + d] = o * inv;
    }
  }
}

// Work unit u: item u / query_parts (scenario * heads + head), query range u % query_parts.
void RunUnit(const Problem& pb, int64_t unit) {
  const int64_t item = unit / pb.query_parts, part = unit % pb.query_parts;
  const int64_t per = (pb.sq + pb.query_parts - 1) / pb.query_parts;
  const int64_t i0 = std::min(pb.sq, part * per), i1 = std::min(pb.sq, i0 + per);
  if (i0 >= i1) return;
  switch (pb.dh) {
    case 16: return RunItem<16>(pb, item, i0, i1);
    case 32: return RunItem<32>(pb, item, i0, i1);
    case 48: return RunItem<48>(pb, item, i0, i1);
    case 64: return RunItem<64>(pb, item, i0, i1);
    case 128: return RunItem<128>(pb, item, i0, i1);
    default: return RunItemGeneric(pb, item, i0, i1);
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
      RunUnit(pb, i);
      ++finished;
    }
    if (finished && done.fetch_add(finished) + finished == total) {
      std::lock_guard<std::mutex> lock(mu);
      cv.notify_all();
    }
  }
};

// K, V: ffi::F32 or ffi::BF16 keys and values (queries and output are float32 either way)
template <ffi::DataType KV>
ffi::Error Attention(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> q, ffi::Buffer<KV> k,
                     ffi::Buffer<KV> v, ffi::Buffer<ffi::S32> q_frame, ffi::Buffer<ffi::S32> num_chunks,
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
  const bool wide = KV == ffi::DataType::F32;
  const void* kp = k.untyped_data();
  const void* vp = v.untyped_data();
  const float* kf = wide ? static_cast<const float*>(kp) : nullptr;
  const float* vf32 = wide ? static_cast<const float*>(vp) : nullptr;
  const uint16_t* kh = wide ? nullptr : static_cast<const uint16_t*>(kp);
  const uint16_t* vh = wide ? nullptr : static_cast<const uint16_t*>(vp);
  shared->pb = Problem{q.typed_data(), kf, vf32, kh, vh, q_frame.typed_data(), num_chunks.typed_data(),
                       out->typed_data(), heads, sq, s, dh, tokens_per_frame, chunk_len, 1};
  const int64_t items = batch * heads;
  if (items == 0 || sq == 0) return ffi::Error::Success();
  // At least four units per thread when there are few (scenario, head) items (batch 1), so that no thread
  // idles at the end; but no part smaller than 16 queries (each part transposes the key blocks again).
  const int64_t threads = std::max<int64_t>(1, pool.num_threads());
  const int64_t want = (4 * threads + items - 1) / items;
  shared->pb.query_parts = std::max<int64_t>(1, std::min<int64_t>(want, sq / 16));
  shared->total = items * shared->pb.query_parts;

  const int64_t helpers = std::min<int64_t>(threads, shared->total) - 1;
  for (int64_t t = 0; t < helpers; ++t) pool.Schedule([shared] { shared->Work(); });
  shared->Work();
  std::unique_lock<std::mutex> lock(shared->mu);
  shared->cv.wait(lock, [&] { return shared->done.load() == shared->total; });
  return ffi::Error::Success();
}

}  // namespace

// The float vector width the kernel was compiled for (16: AVX-512, 8: AVX2, 4: SSE or NEON).
extern "C" int GpdAttentionVectorWidth() { return W; }

XLA_FFI_DEFINE_HANDLER_SYMBOL(GpdBlockCausalAttention, Attention<ffi::DataType::F32>,
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

// The same with a bfloat16 cache (keys and values widened to float32 a block at a time, in L1)
XLA_FFI_DEFINE_HANDLER_SYMBOL(GpdBlockCausalAttentionBf16, Attention<ffi::DataType::BF16>,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::BF16>>()
                                  .Arg<ffi::Buffer<ffi::BF16>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Attr<int64_t>("tokens_per_frame")
                                  .Attr<int64_t>("chunk_len"));
