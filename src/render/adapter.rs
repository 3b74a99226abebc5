//! Choosing the graphics adapter: a real GPU when there is one, else a software one.

use super::RenderError;

/// A high-performance adapter on the requested (or primary) backends, else any adapter there,
/// else any adapter on any backend.
pub(super) fn find_adapter() -> Result<wgpu::Adapter, RenderError> {
    let from_env = wgpu::Backends::from_env();
    let mut tried = Vec::new();
    let candidates = match from_env {
        Some(b) => vec![b],
        None => vec![wgpu::Backends::PRIMARY, wgpu::Backends::all()],
    };
    for backends in candidates {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        desc.backends = backends;
        let instance = wgpu::Instance::new(desc);
        let request = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        }));
        match request {
            Ok(a) => return Ok(a),
            Err(e) => tried.push(format!("{backends:?}: {e}")),
        }
        let mut all = pollster::block_on(instance.enumerate_adapters(backends));
        // Prefer real GPUs, then software adapters; GL cannot copy depth to buffers.
        all.sort_by_key(|a| {
            let i = a.get_info();
            (i.backend == wgpu::Backend::Gl, i.device_type == wgpu::DeviceType::Cpu)
        });
        if let Some(a) = all.into_iter().next() {
            return Ok(a);
        }
    }
    Err(RenderError::NoAdapter(tried.join("; ")))
}
