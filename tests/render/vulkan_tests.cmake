# Vulkan backend tests (included from tests/render/CMakeLists.txt). They run on Mesa lavapipe when
# no GPU is present; they fail (not skip) when no Vulkan device can be created.
streetsim_add_test(NAME vulkan_render_test
                   SOURCES ${CMAKE_CURRENT_LIST_DIR}/vulkan_render_test.cc
                           ${CMAKE_CURRENT_LIST_DIR}/vulkan_reference.cc
                   LIBS streetsim_render_vulkan streetsim_render_api)
