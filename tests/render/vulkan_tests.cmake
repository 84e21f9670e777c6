# Vulkan backend tests (included from tests/render/CMakeLists.txt). They run on Mesa lavapipe when
# no GPU is present; they fail (not skip) when no Vulkan device can be created.
streetsim_add_test(NAME vulkan_render_test
                   SOURCES ${CMAKE_CURRENT_LIST_DIR}/vulkan_render_test.cc
                           ${CMAKE_CURRENT_LIST_DIR}/vulkan_reference.cc
                   LIBS streetsim_render_vulkan streetsim_render_api)
streetsim_add_test(NAME vulkan_backward_test
                   SOURCES ${CMAKE_CURRENT_LIST_DIR}/vulkan_backward_test.cc
                           ${PROJECT_SOURCE_DIR}/tests/common/grad_check_scene.cc
                   LIBS streetsim_render_vulkan streetsim_render_cpu streetsim_render_api
                        streetsim_gaussians)
streetsim_add_test(NAME vulkan_deterministic_test
                   SOURCES ${CMAKE_CURRENT_LIST_DIR}/vulkan_deterministic_test.cc
                   LIBS streetsim_render_vulkan streetsim_render_cpu streetsim_render_api
                        streetsim_gaussians)
# The backward at lavapipe subgroup sizes 4 and 16 (the default run above is 8 on AVX2 hosts).
foreach(width 128 512)
  add_test(NAME vulkan_backward_test_lp${width}
           COMMAND vulkan_backward_test
                   --gtest_filter=VulkanBackward.AgreesWithCpuBackward:VulkanBackward.CompareAndSwapFallbackAgrees:VulkanBackward.DeterministicAgreesWithFiniteDifferences:VulkanBackward.DeterministicLongTileLists)
  set_tests_properties(vulkan_backward_test_lp${width} PROPERTIES
                       ENVIRONMENT "LP_NATIVE_VECTOR_WIDTH=${width}")
  add_test(NAME vulkan_deterministic_test_lp${width}
           COMMAND vulkan_deterministic_test
                   --gtest_filter=VulkanDeterministic.IdenticalBitsAcrossCallsForwardsAndEngines)
  set_tests_properties(vulkan_deterministic_test_lp${width} PROPERTIES
                       ENVIRONMENT "LP_NATIVE_VECTOR_WIDTH=${width}")
endforeach()
