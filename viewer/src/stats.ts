// Frame statistics for the fps / frame-time readout (a fixed-size ring: constant cost per frame).
const N = 120;

export class FrameStats {
  private cpu = new Float64Array(N);
  private stamp = new Float64Array(N);
  private count = 0;
  private next = 0;
  private shown = 0;

  record(cpuMs: number, now: number): void {
    this.cpu[this.next] = cpuMs;
    this.stamp[this.next] = now;
    this.next = (this.next + 1) % N;
    this.count = Math.min(this.count + 1, N);
  }

  /** True about four times a second (when the readout should refresh). */
  due(now: number): boolean {
    if (now - this.shown < 250) return false;
    this.shown = now;
    return true;
  }

  summary(): { fps: number; frameMs: number; intervalMs: number; frames: number } {
    if (this.count < 2) return { fps: 0, frameMs: 0, intervalMs: 0, frames: this.count };
    let sum = 0;
    for (let i = 0; i < this.count; i++) sum += this.cpu[i];
    const newest = this.stamp[(this.next - 1 + N) % N];
    const oldest = this.stamp[(this.next - this.count + N) % N];
    const interval = (newest - oldest) / (this.count - 1);
    return { fps: interval > 0 ? 1000 / interval : 0, frameMs: sum / this.count, intervalMs: interval, frames: this.count };
  }
}
