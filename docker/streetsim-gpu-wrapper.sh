#!/bin/sh
# /usr/local/bin/streetsim in the GPU image (docker/Dockerfile.gpu): points the Vulkan loader at the
# NVIDIA driver's ICD, then runs the real binary in this process (exec: signals reach it unchanged).
#
# The NVIDIA container toolkit mounts the driver, and with the `graphics` capability its Vulkan ICD
# manifest, into the container; where that manifest lands depends on the host's driver install:
# /etc/vulkan/icd.d or /usr/share/vulkan/icd.d (which the loader searches on its own) or
# /usr/local/nvidia/share/vulkan/icd.d (driver installers that keep the driver under /usr/local/nvidia,
# which it does not). The same search as scripts/gpu-bundle-app's. A VK_ICD_FILENAMES or
# VK_DRIVER_FILES set by the caller wins; with no manifest found the loader searches as usual, and
# `--backend vulkan` then fails with the loader's error instead of running somewhere unexpected.
if [ -z "${VK_ICD_FILENAMES:-}" ] && [ -z "${VK_DRIVER_FILES:-}" ]; then
  for icd in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd*.json \
             /etc/vulkan/icd.d/nvidia_icd*.json; do
    if [ -f "$icd" ]; then
      export VK_ICD_FILENAMES="$icd" VK_DRIVER_FILES="$icd"
      break
    fi
  done
fi
exec /usr/local/lib/streetsim/streetsim "$@"
