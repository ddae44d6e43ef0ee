from .fused_bp import fused_bp_available, fused_bp_segment_sum

__all__ = ['fused_bp_available', 'fused_bp_segment_sum']
