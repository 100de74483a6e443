"""XLA flags of every test process (set by conftest.py before JAX starts, inherited by
subprocesses and notebook kernels): the tests compile hundreds of small programs and run each
briefly, so XLA's CPU compile time dominates the suite; these flags make the compiler do less
work (the legacy emitters for fused loops, no expensive LLVM passes) at no cost to what the
tests check (the programs compute the same thing; the numbers may differ in the last bits
from the default code generation)."""

TEST_XLA_FLAGS = "--xla_cpu_use_fusion_emitters=false --xla_llvm_disable_expensive_passes=true"
