// Large arrays on 2 MB pages (transparent huge pages) where the kernel allows it.
//
// Why: the simplification reads per-vertex and per-cell arrays of hundreds of MB at scattered
// places (the greedy queue visits the mesh in error order). With 4 KB pages nearly every such
// read also misses the TLB; one 2 MB entry covers 512 of them. Debian's kernel hands out huge
// pages only where a program asks (THP mode "madvise"), so ask for the big arrays.
#pragma once

#include <sys/mman.h>

#include <cstddef>
#include <cstdint>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

namespace decima {

// Advises the kernel to back the 2 MB-aligned interior of [data, data + bytes) with huge pages.
// Only pages not yet touched are affected, so call it before the array is first written. A
// kernel without THP, or one that refuses, leaves the memory as it was: a hint, never an error.
inline void AdviseHugePages(void* data, size_t bytes) {
#ifdef MADV_HUGEPAGE
  constexpr uintptr_t kHuge = uintptr_t{2} << 20;
  const uintptr_t begin = (reinterpret_cast<uintptr_t>(data) + kHuge - 1) & ~(kHuge - 1);
  const uintptr_t end = (reinterpret_cast<uintptr_t>(data) + bytes) & ~(kHuge - 1);
  if (end > begin) madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE);
#else
  (void)data;
  (void)bytes;
#endif
}

// v.assign(n, value), with v's buffer advised for huge pages before it is written.
template <typename T, typename A>
void AssignOnHugePages(std::vector<T, A>* v, size_t n, const std::type_identity_t<T>& value) {
  v->clear();
  v->reserve(n);
  AdviseHugePages(v->data(), n * sizeof(T));
  v->assign(n, value);
}

// The allocator of large arrays that their owner fills itself, in parallel: cache-line aligned,
// advised for huge pages when allocated, and constructing an element without a value leaves it
// uninitialised (default-init). With std::allocator, vector::resize zero-fills the whole array
// in one thread, which is also where every page is first touched: 0.4-1.4 s for the 426 MB of
// quadrics on Colin27. With this one, the page faults happen in the threads that fill it.
template <typename T>
struct FillLaterAllocator {
  using value_type = T;
  FillLaterAllocator() = default;
  template <typename U>
  FillLaterAllocator(const FillLaterAllocator<U>&) {}
  T* allocate(size_t n) {
    T* p = static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64)));
    AdviseHugePages(p, n * sizeof(T));
    return p;
  }
  void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t(64)); }
  template <typename U>
  void construct(U* p) noexcept(std::is_nothrow_default_constructible_v<U>) {
    ::new (static_cast<void*>(p)) U;
  }
  template <typename U, typename... Args>
  void construct(U* p, Args&&... args) {
    ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
  }
  bool operator==(const FillLaterAllocator&) const { return true; }
};

}  // namespace decima
