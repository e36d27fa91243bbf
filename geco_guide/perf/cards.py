"""The GPUs the cost model predicts for: their data sheets' numbers, and their memory as the planner sees it."""

from __future__ import annotations

__all__ = ["GPU_SPECS", "H200_MEASURED_ESTIMATORS_S", "H200_MEASURED_UPDATES", "H200_UNGUIDED_STEP_S",
           "HOST_BYTES_PER_S", "INTERCONNECT_BYTES_PER_S", "MEASURED_MEMORY_MIB", "MEASURED_RUNS", "card_memory_gib"]

#: The cards the cost model predicts for: memory (GB = 1e9 bytes), dense (no sparsity) bf16
#: tensor-core peak with fp32 accumulation, and memory bandwidth, from the vendor's data sheets:
#: NVIDIA H200 SXM (141 GB, 989.4 TFLOP/s, 4.8 TB/s), NVIDIA H100 SXM (80 GB, 989.4, 3.35 TB/s),
#: NVIDIA L40S (48 GB, 362.05, 864 GB/s), NVIDIA RTX A6000 (48 GB, 154.8, 768 GB/s), NVIDIA
#: GeForce RTX 4090 (24 GB, 165.2 with fp32 accumulation per the Ada Lovelace architecture
#: whitepaper, 1008 GB/s), NVIDIA L4 (24 GB, 121, 300 GB/s).
GPU_SPECS: dict[str, dict[str, float]] = {
    "H200": {"bf16_flops_per_s": 989.4e12, "bytes_per_s": 4.8e12, "memory_gb": 141},
    "H100": {"bf16_flops_per_s": 989.4e12, "bytes_per_s": 3.35e12, "memory_gb": 80},
    "L40S": {"bf16_flops_per_s": 362.05e12, "bytes_per_s": 864e9, "memory_gb": 48},
    "A6000": {"bf16_flops_per_s": 154.8e12, "bytes_per_s": 768e9, "memory_gb": 48},
    "RTX4090": {"bf16_flops_per_s": 165.2e12, "bytes_per_s": 1008e9, "memory_gb": 24},
    "L4": {"bf16_flops_per_s": 121e12, "bytes_per_s": 300e9, "memory_gb": 24},
}
#: Measured on the H200 (docs/benchmarks/sampling_full_h200_*.json): one unguided CFG step of the
#: CogVideoX-5B transformer at 49x480x720, steady state (steps 2-4 of the three unguided arms).
H200_UNGUIDED_STEP_S = 1.78

#: Measured on the H200 (docs/benchmarks/sampling_full_h200_fast.json and _faithful.json): VGGT's
#: and UFM's forward seconds over the 111 updates of the paper's schedule in each guided run (what a
#: search's scoring runs, without the backward; the loss's measured seconds hold its backward too).
H200_MEASURED_ESTIMATORS_S = {"fast": {"vggt": 19.3, "ufm": 8.4}, "faithful": {"vggt": 10.9, "ufm": 6.4}}
H200_MEASURED_UPDATES = 111
MEASURED_RUNS = tuple(H200_MEASURED_ESTIMATORS_S)

#: One direction's bandwidth from one GPU to the others of its node (bytes/s), from the data
#: sheets: NVLink 4 on the H200 and H100 SXM (18 links, 900 GB/s both ways, through the NVSwitch
#: to every other GPU of an HGX board), PCIe 4.0 x16 for the PCIe cards (32 GB/s; an A6000 pair's
#: NVLink bridge is faster, the common node has none). The collectives of several GPUs are
#: predicted at this rate: an upper bound on what NCCL reaches.
INTERCONNECT_BYTES_PER_S = {"H200": 450e9, "H100": 450e9, "L40S": 32e9, "A6000": 32e9, "RTX4090": 32e9, "L4": 32e9}
#: One direction's bandwidth between a card and the host (bytes/s), from the data sheets: PCIe 5.0
#: x16 on the H200 and H100 SXM (128 GB/s both ways), PCIe 4.0 x16 on the others (64 GB/s both
#: ways). What model CPU offload moves its models over.
HOST_BYTES_PER_S = {"H200": 64e9, "H100": 64e9, "L40S": 32e9, "A6000": 32e9, "RTX4090": 32e9, "L4": 32e9}
#: The memory a card reported where one was measured (MiB): the H200 of the GPU runs
#: (docs/performance_records.md, GPU), 143771 MiB = 140.4 GiB, more than its data sheet's 141 GB.
MEASURED_MEMORY_MIB = {"H200": 143771}


def card_memory_gib(gpu: str) -> float:
    """The memory of card ``gpu`` (:data:`GPU_SPECS`) in GiB: what the measured card reported
    (:data:`MEASURED_MEMORY_MIB`) where one was measured, else its data sheet's (GB of 10^9 bytes)."""
    if gpu in MEASURED_MEMORY_MIB:
        return MEASURED_MEMORY_MIB[gpu] / 1024
    return GPU_SPECS[gpu]["memory_gb"] * 1e9 / 2**30
